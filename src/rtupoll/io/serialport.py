"""Serial ports: opening them without resetting the device, and saying why they won't open.

DTR. Linux raises DTR and RTS when a tty is opened, and some boards (CO2Meter's
AN117 family) are held in reset while DTR is asserted. pymodbus opens the port
itself (``serial.serial_for_url`` in its serial transport) and has no option for the
modem lines, so the one hook that leaves pymodbus untouched is pyserial's public
URL-handler extension: ``nodtr:///dev/ttyUSB0`` makes ``serial_for_url`` build the
``Serial`` class below, which clears DTR and RTS *before* ``open()``; pyserial then
writes that state right after the open system call, before a byte is exchanged.
(The kernel's raise-on-open itself cannot be prevented from user space; what this
removes is the seconds-long assertion that holds such a board in reset.)

rtupoll's own port. ``Bus`` has pymodbus open every serial port as
``rtupoll://N/dev/ttyUSB0`` (``claim``): the same hook builds a ``Serial`` bound to
``Slot`` N, which holds the open ``Serial`` object for the bus. So the bus writes a
frame to it at once and looks at what waits in it through pyserial's public API,
never through pymodbus's transport internals; and the slot's ``rs485`` settings are
applied on open (``direction_control``: the kernel's RS-485 mode, TIOCSRS485, where
the driver has it, else ``RtsToggle`` around each write; a port with neither is a
one-line error). ``nodtr://PATH`` stays a port name users may give.

Naming. pyserial finds a scheme ``X`` by importing ``<package>.protocol_X`` for
each package in ``serial.protocol_handler_packages``. Rather than ship a package
with a ``protocol_nodtr`` module, this module registers itself in ``sys.modules``
under ``rtupoll.io.serialport.protocol_nodtr`` and appends ``rtupoll.io.serialport`` to
that list (``register()``, idempotent, called on import). ``serial_class_for_url``
strips the scheme, so the port pyserial opens is the plain device path.

Errors. A port that will not open is the commonest field problem, and "could not
open port" helps nobody. ``open_error`` and ``gateway_error`` turn the OS error
into what to do: missing (unplugged?), busy (another program holds it: pyserial's
exclusive lock), permission denied (which group to join), not a serial port,
gateway refused / unreachable / not answering.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import os
import sys
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial
import serial.rs485

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.rtu import Framing

SCHEME = "nodtr"
_PREFIX = f"{SCHEME}://"
OWN = "rtupoll"  # rtupoll://N/dev/ttyUSB0: the port of ``Slot`` N (``claim``)
_OWN_PREFIX = f"{OWN}://"


@frozen
class Rs485:
    """Direction control for a transceiver whose DE/RE pin is on RTS: RTS is raised
    ``before`` seconds before a frame's first bit and dropped ``after`` seconds after
    its last. The kernel's RS-485 mode (TIOCSRS485, pyserial's ``rs485_mode``) does it
    where the driver has it; else rtupoll toggles RTS around each write."""

    before: float = 0.0
    after: float = 0.0


class RtsToggle:
    """RTS driven around each write, for a driver without kernel RS-485 mode: up,
    ``before``, the frame, wait until its last bit has left (``flush``: tcdrain),
    ``after``, down. ``port`` is any object with pyserial's ``rts`` and ``flush``."""

    def __init__(self, port: Any, rs485: Rs485,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.port, self.rs485, self._sleep = port, rs485, sleep

    def write(self, write: Callable[[bytes], int | None], data: bytes) -> int | None:
        self.port.rts = True
        if self.rs485.before:
            self._sleep(self.rs485.before)
        try:
            sent = write(data)
            self.port.flush()
            if self.rs485.after:
                self._sleep(self.rs485.after)
        finally:
            self.port.rts = False
        return sent


def direction_control(port: Any, rs485: Rs485) -> tuple[str, RtsToggle | None]:
    """Set up ``rs485`` on an open ``port``: ("kernel", None) when the driver does it,
    ("rts", the toggler) when RTS can be driven instead; ``UsageError`` (one line) when
    the port can do neither."""
    name = getattr(port, "port", None) or "the port"
    try:
        port.rs485_mode = serial.rs485.RS485Settings(
            rts_level_for_tx=True, rts_level_for_rx=False,
            delay_before_tx=rs485.before, delay_before_rx=rs485.after)
        return "kernel", None
    except (ValueError, OSError, serial.SerialException, NotImplementedError) as exc:
        kernel = str(exc) or type(exc).__name__
        with contextlib.suppress(Exception):
            port.rs485_mode = None
    try:
        port.rts = False  # receiving: the transceiver listens
    except (ValueError, OSError, serial.SerialException) as exc:
        raise UsageError(f"{name} supports neither the kernel's RS-485 mode ({kernel}) nor "
                         f"RTS control ({exc or type(exc).__name__}): --rs485 needs a UART "
                         "with RTS wired to the transceiver's DE/RE, or an adapter that "
                         "switches direction by itself (then leave --rs485 out)") from None
    return "rts", RtsToggle(port, rs485)


@frozen
class PortSettings:
    """One bus's port and line settings (both drivers take them: ``rtupoll.io.bus.Bus``,
    ``rtupoll.io.syncbus.SyncBus``)."""

    port: str  # "/dev/ttyUSB0", a pty path, or "tcp://HOST:PORT" (RTU over a TCP gateway)
    baudrate: int = 9600
    parity: str = "N"
    bytesize: int = 8
    stopbits: int = 1
    deassert_dtr: bool = False  # open with DTR/RTS deasserted (CO2Meter boards reset on DTR)
    echo: bool = False  # the adapter echoes each request: the line consumes the echo
    rs485: Rs485 | None = None  # drive the transceiver's direction (RTS)
    idle_gap: float = 0.0  # silence every device gets before a request (``Line.idle_gap``)

    @property
    def framing(self) -> Framing:
        return Framing(self.baudrate, self.bytesize, self.parity, self.stopbits)

    @property
    def gateway(self) -> tuple[str, int] | None:
        """(host, port) for ``tcp://HOST:PORT``, None for a serial port."""
        return gateway(self.port)


@dataclass
class Slot:
    """One bus's port as pyserial builds it for pymodbus: what to do on open, and the
    ``Serial`` object itself once open (``port``), so the bus may write to it and look
    at what waits in it through pyserial's public API, not pymodbus's internals."""

    deassert_dtr: bool = False
    rs485: Rs485 | None = None
    port: Serial | None = None
    direction: str = ""  # "kernel" or "rts" once open with rs485
    error: str = ""  # why the port opened but cannot be used as asked (one line)
    parity: str = "N"  # the line's parity (a pty, which has none, is marked: pty_parity)


# the bus that claimed a slot holds it; once that bus is gone, so is its slot
_SLOTS: weakref.WeakValueDictionary[int, Slot] = weakref.WeakValueDictionary()
_slot_ids = itertools.count(1)


class Serial(serial.Serial):  # type: ignore[misc]  # pyserial ships no type hints
    """A pyserial port that opens with DTR and RTS deasserted (``slot``: when its
    ``Slot`` says so; ``nodtr://``: always), and tells its ``Slot`` it is open."""

    slot: Slot | None = None
    _toggle: RtsToggle | None = None  # RTS driven around each write (--rs485 without kernel)

    def open(self) -> None:
        # Setting the lines on a closed port only records the state; open() applies it
        # immediately after the open system call (serialposix: _update_dtr_state).
        if self.slot is None or self.slot.deassert_dtr:
            self.dtr = False
            self.rts = False
        super().open()
        self._toggle = None
        slot = self.slot
        if slot is None:
            return
        slot.port, slot.error = self, ""
        if slot.rs485 is not None:
            try:
                slot.direction, self._toggle = direction_control(self, slot.rs485)
            except UsageError as exc:
                slot.error = str(exc)
                self.close()
                raise serial.SerialException(slot.error) from None

    def _reconfigure_port(self, force_update: bool = False) -> None:
        """pyserial's, which every setting (pymodbus sets the timeouts) goes through; then,
        on a pty opened without the line's parity (``line_parity``), the parity marked
        (``pty_parity``): pyserial's own would clear the mark."""
        super()._reconfigure_port(force_update)
        slot = self.slot
        if slot is not None and slot.parity != "N" and self.parity == "N":
            pty_parity(self.fd, slot.parity)

    def read(self, size: int = 1) -> bytes:
        """pyserial's ``read``; on a non-blocking port (``timeout`` 0, as pymodbus's
        transport sets it and reads once the event loop saw bytes waiting) one
        ``os.read`` of what waits, without pyserial's per-call ``Timeout`` and
        ``select``: one system call less each. Nothing read (the port, VMIN 0, says
        the same when nothing waits and when it was hung up) is pyserial's to judge:
        its ``select`` tells the two apart, and a port gone raises as it always did."""
        if self.timeout != 0 or not self.is_open:
            return super().read(size)  # type: ignore[no-any-return]
        try:
            data = os.read(self.fd, size)
        except BlockingIOError:
            data = b""
        except OSError as exc:  # the adapter unplugged (EIO), ...: pyserial's error
            raise serial.SerialException(f"read failed: {exc}") from None
        if data:
            return data
        return super().read(size)  # type: ignore[no-any-return]

    def write(self, data: bytes) -> int | None:
        """pyserial's ``write``; on a non-blocking port (``write_timeout`` 0, as pymodbus's
        transport sets it) with no RTS to toggle, one ``os.write``: what fitted is
        returned (0 when the port's buffer is full, where pyserial would spin until
        all of it went), the caller hands the rest to the transport."""
        if self._toggle is None:
            if self.write_timeout != 0 or not self.is_open:
                return super().write(data)  # type: ignore[no-any-return]
            try:
                return os.write(self.fd, data)
            except BlockingIOError:
                return 0
            except OSError as exc:
                raise serial.SerialException(f"write failed: {exc}") from None
        return self._toggle.write(super().write, data)


def serial_class_for_url(url: str) -> tuple[str, type[Serial]]:
    """pyserial's handler hook: ``nodtr:///dev/ttyUSB0`` -> (``/dev/ttyUSB0``, Serial);
    ``rtupoll://N/dev/ttyUSB0`` -> (``/dev/ttyUSB0``, a Serial bound to slot N)."""
    low = url.lower()
    if low.startswith(_PREFIX):
        return url[len(_PREFIX):], Serial
    if low.startswith(_OWN_PREFIX):
        number, _, path = url[len(_OWN_PREFIX):].partition("/")
        slot = _SLOTS.get(int(number)) if number.isdigit() else None
        if slot is not None:
            return "/" + path, type("Serial", (Serial,), {"slot": slot})
    raise serial.SerialException(f"expected a {_PREFIX} URL, got {url!r}")


def register() -> None:
    """Make ``nodtr://`` and ``rtupoll://`` known to ``serial.serial_for_url`` (idempotent)."""
    for scheme in (SCHEME, OWN):
        sys.modules.setdefault(f"{__name__}.protocol_{scheme}", sys.modules[__name__])
    if __name__ not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(__name__)


def claim(port: str, *, deassert_dtr: bool, rs485: Rs485 | None = None, parity: str = "N"
          ) -> tuple[str, Slot | None]:
    """The URL pymodbus is to open ``port`` with, and the ``Slot`` that will hold the
    ``Serial`` object: for a device path (and ``nodtr://``), ``rtupoll://N/PATH``; other
    URLs (``socket://``, ``rfc2217://``) pass unchanged, with no slot. ``parity``: the
    line's (a pty opened without it is marked with it, ``pty_parity``)."""
    if port.lower().startswith(_PREFIX):
        port, deassert_dtr = port[len(_PREFIX):], True
    if "://" in port or not port.startswith("/"):
        if rs485 is not None:
            raise UsageError(f"{port}: --rs485 drives a serial port's RTS line; this is not "
                             "a serial port")
        return port_url(port, deassert_dtr=deassert_dtr), None
    number = next(_slot_ids)
    slot = Slot(deassert_dtr=deassert_dtr, rs485=rs485, parity=parity)
    _SLOTS[number] = slot
    return f"{_OWN_PREFIX}{number}{port}", slot


def release(url: str) -> None:
    """Forget the slot of a ``claim``ed URL (its bus is closed for good)."""
    if url.lower().startswith(_OWN_PREFIX):
        number = url[len(_OWN_PREFIX):].partition("/")[0]
        if number.isdigit():
            _SLOTS.pop(int(number), None)


def port_url(port: str, *, deassert_dtr: bool) -> str:
    """The URL to give pyserial: ``nodtr://`` for a device path when DTR must stay low.

    Other URLs (``socket://``, ``rfc2217://``) have no modem lines and pass unchanged.
    """
    if deassert_dtr and "://" not in port:
        return _PREFIX + port
    return port


def gateway(port: str) -> tuple[str, int] | None:
    """(host, port) of an RTU-over-TCP gateway ``tcp://HOST:PORT``; None for anything else."""
    if not port.lower().startswith("tcp://"):
        return None
    host, _, number = port[6:].rstrip("/").rpartition(":")
    if not host or not number.isdigit() or not 0 < int(number) < 65536:
        raise UsageError(f"{port!r}: expected tcp://HOST:PORT")
    return host.strip("[]"), int(number)


def device_path(port: str) -> str:
    """The filesystem path behind a port, ``nodtr://`` or ``rtupoll://N`` URL."""
    if port.lower().startswith(_OWN_PREFIX):
        return "/" + port[len(_OWN_PREFIX):].partition("/")[2]
    return port[len(_PREFIX):] if port.lower().startswith(_PREFIX) else port


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


def open_error(port: str, exc: BaseException) -> str:
    """One line saying why ``port`` did not open, and what to do about it."""
    path = device_path(port)
    code = getattr(exc, "errno", None)
    text = str(exc)
    if code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY) or "exclusively lock" in text:
        return (f"{path} is busy: another program has it open (close it, or stop the "
                f"service using it: 'fuser {path}' shows which)")
    if code in (errno.EACCES, errno.EPERM):
        group = _group_of(path)
        join = f"; add yourself to the '{group}' group and log in again" if group else ""
        return f"permission denied opening {path}{join}"
    if code in (errno.ENOENT, errno.ENXIO, errno.ENODEV) or (
            code is None and not os.path.exists(path) and "://" not in path):
        import glob

        seen = sorted(glob.glob("/dev/ttyUSB*") + glob.glob("/dev/ttyACM*"))
        hint = f" (serial ports present: {', '.join(seen)})" if seen else \
            " (is the adapter plugged in?)"
        return f"{path} does not exist{hint}"
    if code in (errno.ENOTTY, errno.EINVAL) or f"({errno.ENOTTY}, " in text:
        # pyserial reports a failed termios call as "Could not configure port: (25, ...)"
        return f"{path} is not a serial port"
    if isinstance(exc, ValueError):
        return f"{path}: {text}"
    return f"cannot open {path}: {text or type(exc).__name__}"


def gateway_error(host: str, port: int, exc: BaseException, timeout: float) -> str:
    """One line saying why an RTU-over-TCP gateway did not accept a connection."""
    import socket

    where = f"gateway {host}:{port}"
    if isinstance(exc, ConnectionRefusedError):
        return f"{where} refused the connection (wrong port, or the gateway allows one client)"
    if isinstance(exc, socket.gaierror):
        return f"{where}: cannot resolve {host!r}"
    if isinstance(exc, TimeoutError):  # asyncio's too (3.11+)
        return f"{where} did not answer within {timeout:g} s (unreachable or filtered)"
    code = getattr(exc, "errno", None)
    if code in (errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EHOSTDOWN):
        return f"{where} is unreachable ({os.strerror(code)})"
    return f"cannot connect to {where}: {exc or type(exc).__name__}"


def diagnose_serial(url: str, **settings: Any) -> str | None:
    """Try to open ``url`` the way pymodbus does; why it fails, or None if it opens.

    Used only after a failed open, to name the reason (pymodbus swallows it).
    """
    try:
        port = serial.serial_for_url(url, exclusive=True, **settings)
    except (OSError, ValueError) as exc:
        return open_error(url, exc)
    port.close()
    return None


async def diagnose_gateway(host: str, port: int, timeout: float) -> str | None:
    """Try a plain TCP connection; why it fails, or None if it connects."""
    import asyncio

    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    except (TimeoutError, OSError) as exc:
        return gateway_error(host, port, exc, timeout)
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return None


LATENCY_OK = 0.001  # seconds: an adapter latency timer above this is worth lowering
UDEV_RULE = ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", '
             'ATTR{latency_timer}="1"')


def latency_timer(port: str, *, root: str = "/") -> float | None:
    """A USB-serial adapter's latency timer in seconds (Linux: ``/sys/bus/usb-serial/
    devices/ttyUSBn/latency_timer``, in ms), or None for any other port or when unknown.

    The adapter holds received bytes up to this long before passing them on (FTDI: 16 ms
    by default), so every reply seems that much slower. ``root``: where ``/sys`` and
    ``/dev`` are looked up (tests give a directory tree of their own)."""
    if "://" in port.replace(_PREFIX, ""):
        return None
    path = device_path(port)
    if root != "/":
        path = os.path.join(root, path.lstrip("/"))
    tty = os.path.basename(os.path.realpath(path))
    if not tty.startswith("ttyUSB"):
        return None
    try:
        with open(os.path.join(root, "sys/bus/usb-serial/devices", tty, "latency_timer")) as f:
            return int(f.read().strip()) / 1000
    except (OSError, ValueError):
        return None


def latency_warning(port: str, latency: float | None) -> str | None:
    """One line for the user when ``port``'s adapter latency timer is above 1 ms."""
    if latency is None or latency <= LATENCY_OK:
        return None
    tty = os.path.basename(os.path.realpath(device_path(port)))
    return (f"{port}: the USB adapter's latency timer is {latency * 1000:g} ms, added to "
            f"every reply; lower it with 'echo 1 | sudo tee /sys/bus/usb-serial/devices/"
            f"{tty}/latency_timer' or for good with the udev rule {UDEV_RULE}")


def _group_of(path: str) -> str:
    try:
        import grp  # POSIX only

        return grp.getgrgid(os.stat(path).st_gid).gr_name
    except (ImportError, OSError, KeyError):
        return ""


register()
