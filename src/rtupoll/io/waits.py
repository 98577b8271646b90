"""The one wait primitive: bytes that arrive on a port within a time, however it offers them.

``wait_on(port)`` gives a ``Wait``: called with the seconds left, it returns what arrived
(``b""``: nothing came in that time) as soon as anything did, or raises ``Gone`` (the
port hung up, the adapter was unplugged, the connection closed). Which one is chosen by
what the port offers, never by the platform's name:

- ``FdWait``: the port has a real file descriptor for a character device (a tty, a pty:
  pyserial's POSIX ``Serial``): ``select`` on it, one ``os.read``; microsecond timeouts.
- ``SocketWait``: a socket (an RTU-over-TCP gateway): ``select`` and ``recv`` (a socket is
  no file on Windows; ``os.read`` is never used on one).
- ``PortWait``: anything else pyserial opens -- a Windows COM port (``serialwin32``: no
  ``fileno``), ``rfc2217://`` (its reader thread fills a queue), ``socket://`` -- through
  pyserial's own API only: ``read`` with the port's ``timeout``, ``in_waiting``.

``PortWait`` sets the port's ``timeout`` once (``SLICE``) and never again: changing it
reconfigures the port (Windows: ``SetCommTimeouts`` and the whole DCB; RFC 2217: a
negotiation with the server that sleeps 50 ms). A wait of ``SLICE`` or more is a
``read(1)``, which returns with the first byte (then ``read(in_waiting)`` takes the
rest); a shorter one (the end of a silence) is slept, and what came meanwhile is read
at its end: stamped then, never earlier than it came, so a silence is never taken for
longer than it was. ``SLICE`` also bounds how long a Ctrl-C waits on Windows, where it
is seen when the read returns.
"""

from __future__ import annotations

import os
import select
import stat
import sys
import time
from collections.abc import Callable
from typing import Any, Protocol

CHUNK = 4096  # bytes read at most at once
SLICE = 0.02  # seconds: PortWait's fixed read timeout (module docstring)


class Gone(Exception):
    """The port is gone: hung up, unplugged, the connection closed."""


class Wait(Protocol):
    def __call__(self, left: float) -> bytes:
        """What arrives within ``left`` seconds (``b""``: nothing); ``Gone``."""
        ...


def real_fd(port: Any) -> int | None:
    """``port``'s file descriptor when it is a character device (a tty, a pty), else None
    (no ``fileno``: Windows's ports, ``rfc2217://``; a socket's: ``socket://``). rtupoll's
    own port says it itself (``OwnPort.device_fd``: its ``fileno`` may be a ``Pump``'s)."""
    if not isinstance(port, super) and hasattr(type(port), "device_fd"):
        return port.device_fd  # type: ignore[no-any-return]
    try:
        fd = port.fileno()
        return fd if isinstance(fd, int) and stat.S_ISCHR(os.fstat(fd).st_mode) else None
    except (OSError, ValueError, AttributeError):  # io.UnsupportedOperation is both
        return None


def wait_on(port: Any, *, sleep: Callable[[float], None] = time.sleep) -> Wait:
    """The wait for an open ``port``: a pyserial ``Serial`` or a plain socket (``sleep``:
    ``PortWait``'s, for tests in virtual time)."""
    sockets = sys.modules.get("socket")  # (not imported: the port is no socket; read's
    if sockets is not None and isinstance(port, sockets.socket):  # start-up skips it)
        return SocketWait(port)
    fd = real_fd(port)
    return FdWait(fd) if fd is not None else PortWait(port, sleep=sleep)


class FdWait:
    """``select`` and ``os.read`` on a character device's descriptor (POSIX)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __call__(self, left: float) -> bytes:
        ready, _, _ = select.select([self.fd], [], [], max(left, 0.0))
        if not ready:
            return b""
        try:
            data = os.read(self.fd, CHUNK)
        except BlockingIOError:
            return b""  # (a non-blocking port: nothing after all)
        except OSError as exc:  # EIO: the adapter unplugged
            raise Gone(exc.strerror or str(exc)) from None
        if not data:  # readable, yet nothing: hung up
            raise Gone("the port hung up")
        return data


class SocketWait:
    """``select`` and ``recv`` on a socket (portable: Windows's ``select`` takes sockets)."""

    def __init__(self, sock: Any) -> None:
        self.sock = sock

    def __call__(self, left: float) -> bytes:
        ready, _, _ = select.select([self.sock], [], [], max(left, 0.0))
        if not ready:
            return b""
        try:
            data: bytes = self.sock.recv(CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise Gone(exc.strerror or str(exc)) from None
        if not data:
            raise Gone("the connection was closed")
        return data


# Wine (8.0) ends a COM port's read whose timeout ran out with ERROR_TIMEOUT, which
# pyserial's Windows backend raises ("GetOverlappedResult failed (OSError(22, 'Timeout.',
# None, 1460))"); Windows completes it with the bytes read so far (none), as a timeout
ERROR_TIMEOUT = 1460


def timed_out(exc: Exception) -> bool:
    """pyserial's error for a read that only timed out (Wine: ``ERROR_TIMEOUT``)."""
    return f", {ERROR_TIMEOUT}))" in str(exc)


class PortWait:
    """pyserial's own ``read``/``in_waiting``, for a port with no descriptor to wait on."""

    def __init__(self, port: Any, *, sleep: Callable[[float], None] = time.sleep) -> None:
        self.port, self._sleep = port, sleep
        if port.timeout != SLICE:
            port.timeout = SLICE  # once (module docstring)

    def __call__(self, left: float) -> bytes:
        import serial

        port = self.port
        try:
            if left >= SLICE:
                try:
                    first: bytes = port.read(1)  # returns with the first byte, or after SLICE
                except serial.SerialException as exc:
                    if not timed_out(exc):
                        raise
                    return b""
                if not first:
                    return b""
                waiting = port.in_waiting
                return first + port.read(waiting) if waiting else first
            if left > 0:
                self._sleep(left)
            waiting = port.in_waiting
            return port.read(waiting) if waiting else b""
        except (serial.SerialException, OSError) as exc:  # unplugged, the connection lost
            raise Gone(str(exc) or type(exc).__name__) from None


class Pump:
    """A descriptor for a port that has none, for an event loop to wait on (pymodbus's
    transport on POSIX: ``add_reader``): a thread waits on the port (a ``PortWait``) and
    passes what arrives through a socket pair; the loop reads the other end. A port
    gone ends the thread and closes its end: the next ``read`` raises pyserial's error."""

    def __init__(self, wait: Wait) -> None:
        import socket
        import threading

        self._wait = wait
        self._r, self._w = socket.socketpair()
        self._r.setblocking(False)
        self._gone = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rtupoll-port-pump",
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                data = self._wait(SLICE)
                if data:
                    self._w.sendall(data)
        except Gone as exc:
            self._gone = str(exc)
        except OSError:  # closed under it
            pass
        finally:
            self._w.close()

    def fileno(self) -> int:
        return self._r.fileno()

    def in_waiting(self) -> int:
        """1 when something waits to be read (or the port is gone), else 0."""
        ready, _, _ = select.select([self._r], [], [], 0)
        return len(ready)

    def read(self, size: int) -> bytes:
        import serial

        try:
            data = self._r.recv(size)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise serial.SerialException(f"read failed: {exc}") from None
        if not data:
            raise serial.SerialException(self._gone or "the port went away")
        return data

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)  # it wakes within SLICE
        self._r.close()
