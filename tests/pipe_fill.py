"""What a test reads of a pipe it holds without reading it (a reader that stalls)."""

from __future__ import annotations

import fcntl
import termios


def in_pipe(fd: int) -> int:
    """Bytes in the pipe ``fd`` reads, not yet read."""
    return int.from_bytes(fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"), "little")
