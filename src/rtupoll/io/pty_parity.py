"""A line's parity on a pseudo-terminal (the simulator's), which has no wire and no
parity bit: a pty is opened without parity (``line_parity``), then marked with the
line's (``pty_parity``) the way libmodbus marks it, and the simulator reads the mark from
its side (``pty_parity_of``), so it answers a master only at its line's parity."""

from __future__ import annotations

import contextlib
import os

from rtupoll.io.port_names import device_path


def line_parity(port: str, parity: str) -> str:
    """The parity to open ``port`` with: a pseudo-terminal (the simulator's) has no wire
    and no parity bit, and Linux refuses to set one on it after its first open (EINVAL),
    so a pty is opened without; the framing, and so the timing, keeps ``parity``."""
    return "N" if os.path.realpath(device_path(port)).startswith("/dev/pts/") else parity


def pty_parity(fd: int, parity: str) -> None:
    """Say ``parity`` on a pty the way the kernel lets it be said: a pty has no parity bit
    (Linux clears PARENB on it), but keeps input parity checking (INPCK, the receiver
    checks parity: there is one) and PARODD. libmodbus (mbpoll) sets the same flags for
    E and O, so the simulator, reading them from its side (``sim.server``), answers a
    master only at its line's parity, as on a wire. Best effort: no error is raised."""
    import termios

    with contextlib.suppress(OSError, termios.error):
        attrs = termios.tcgetattr(fd)
        attrs[0] |= termios.INPCK
        attrs[2] = (attrs[2] | termios.PARENB | termios.PARODD) if parity == "O" else \
            (attrs[2] | termios.PARENB) & ~termios.PARODD
        termios.tcsetattr(fd, termios.TCSANOW, attrs)


def pty_parity_of(fd: int) -> str:
    """The parity a master set on a pty, as ``pty_parity`` (or libmodbus) says it: N, E, O."""
    import termios

    try:
        iflag, _, cflag = termios.tcgetattr(fd)[:3]
    except (OSError, termios.error):
        return "N"
    if not iflag & termios.INPCK and not cflag & termios.PARENB:
        return "N"
    return "O" if cflag & termios.PARODD else "E"
