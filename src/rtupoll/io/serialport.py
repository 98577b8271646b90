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

Errors. Why a port will not open is ``rtupoll.io.port_errors``'s to say (``diagnose_serial``
and ``diagnose_gateway`` find the error after pymodbus swallowed it); an adapter's
latency timer is ``rtupoll.io.latency``'s.
"""

from __future__ import annotations

import contextlib
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
NETWORK = ("rfc2217://", "socket://")  # pyserial's serial ports over a network


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
    port: Any = None  # the OwnPort (a Serial, or an OwnPort over a URL's class)
    direction: str = ""  # "kernel" or "rts" once open with rs485
    error: str = ""  # why the port opened but cannot be used as asked (one line)
    parity: str = "N"  # the line's parity (a pty, which has none, is marked: pty_parity)


# the bus that claimed a slot holds it; once that bus is gone, so is its slot
_SLOTS: weakref.WeakValueDictionary[int, Slot] = weakref.WeakValueDictionary()
_slot_ids = itertools.count(1)


class OwnPort:
    """What rtupoll's port adds to the pyserial class that opens it (a device's
    ``serial.Serial``; for ``rfc2217://`` and ``socket://`` the URL's own class): DTR and
    RTS deasserted before the open (``slot``: when its ``Slot`` says so; ``nodtr://``:
    always), its ``Slot`` told it is open, one system call per read and write where the
    port is a descriptor, ``write_timeout = 0`` (pymodbus's) taken by a port that refuses
    it (RFC 2217's client) as no write timeout, and, for a port with no descriptor, one
    to wait on (``fileno``: a ``waits.Pump``), so pymodbus's event loop can."""

    slot: Slot | None = None
    _toggle: RtsToggle | None = None  # RTS driven around each write (--rs485 without kernel)
    _pump: Any = None  # a waits.Pump once a descriptor was asked of a port with none

    def open(self: Any) -> None:
        # Setting the lines on a closed port only records the state; open() applies it
        # immediately after the open system call (serialposix: _update_dtr_state).
        if self.slot is None or self.slot.deassert_dtr:
            self.dtr = False
            self.rts = False
        super().open()  # type: ignore[misc]
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

    def close(self: Any) -> None:
        pump, self._pump = self._pump, None
        if pump is not None:
            pump.close()
        super().close()  # type: ignore[misc]

    @property
    def pumped(self) -> bool:
        """Whether reads come from a ``waits.Pump`` (non-blocking, whatever ``timeout``)."""
        return self._pump is not None

    @property
    def device_fd(self: Any) -> int | None:
        """The port's own descriptor when it is a character device, else None."""
        from rtupoll.io import waits

        return waits.real_fd(super())

    def fileno(self: Any) -> int:
        """The port's descriptor; for a port with none (``rfc2217://``), that of a
        ``waits.Pump``, which a thread fills with what the port receives."""
        if self._pump is None:
            try:  # a device's, or socket://'s own socket
                return super().fileno()  # type: ignore[misc,no-any-return]
            except (OSError, ValueError, AttributeError):  # none (io.UnsupportedOperation)
                from rtupoll.io import waits

                self.timeout = waits.SLICE  # the pump's reads wait; ours read its socket
                self._pump = waits.Pump(waits.PortWait(_Base(self)))
        return self._pump.fileno()  # type: ignore[no-any-return]

    @property
    def in_waiting(self: Any) -> int:
        if self._pump is not None:
            return self._pump.in_waiting()  # type: ignore[no-any-return]
        return super().in_waiting  # type: ignore[misc,no-any-return]

    @property
    def write_timeout(self: Any) -> float | None:
        return self._write_timeout  # type: ignore[no-any-return]

    @write_timeout.setter
    def write_timeout(self: Any, value: float | None) -> None:
        setter = serial.SerialBase.write_timeout.fset
        try:
            setter(self, value)
        except NotImplementedError:  # RFC 2217's client: "write_timeout is not supported"
            setter(self, None)  # its writes are a socket's sendall: they never wait long

    def _reconfigure_port(self: Any, *args: Any, **kwargs: Any) -> None:
        """pyserial's, which every setting (pymodbus sets the timeouts) goes through; then,
        on a pty opened without the line's parity (``line_parity``), the parity marked
        (``pty_parity``): pyserial's own would clear the mark."""
        super()._reconfigure_port(*args, **kwargs)  # type: ignore[misc]  # (URL classes: none)
        slot = self.slot
        if slot is not None and slot.parity != "N" and self.parity == "N" and \
                getattr(self, "fd", None) is not None:
            pty_parity(self.fd, slot.parity)

    def read(self: Any, size: int = 1) -> bytes:
        """pyserial's ``read``; on a non-blocking port (``timeout`` 0, as pymodbus's
        transport sets it and reads once the event loop saw bytes waiting) one
        ``os.read`` of what waits, without pyserial's per-call ``Timeout`` and
        ``select``: one system call less each. Nothing read (the port, VMIN 0, says
        the same when nothing waits and when it was hung up) is pyserial's to judge:
        its ``select`` tells the two apart, and a port gone raises as it always did.
        A port with no descriptor (Windows, ``rfc2217://``) reads as pyserial reads it,
        or from its ``Pump`` once it has one."""
        if self._pump is not None:
            return self._pump.read(size)  # type: ignore[no-any-return]
        fd = getattr(self, "fd", None)
        if self.timeout != 0 or not self.is_open or not isinstance(fd, int):
            return super().read(size)  # type: ignore[misc,no-any-return]
        try:
            data = os.read(fd, size)
        except BlockingIOError:
            data = b""
        except OSError as exc:  # the adapter unplugged (EIO), ...: pyserial's error
            raise serial.SerialException(f"read failed: {exc}") from None
        if data:
            return data
        return super().read(size)  # type: ignore[misc,no-any-return]

    def write(self: Any, data: bytes) -> int | None:
        """pyserial's ``write``; on a non-blocking port (``write_timeout`` 0, as pymodbus's
        transport sets it) with no RTS to toggle, one ``os.write``: what fitted is
        returned (0 when the port's buffer is full, where pyserial would spin until
        all of it went), the caller hands the rest to the transport."""
        if self._toggle is None:
            fd = getattr(self, "fd", None)
            if self.write_timeout != 0 or not self.is_open or not isinstance(fd, int):
                return super().write(data)  # type: ignore[misc,no-any-return]
            try:
                return os.write(fd, data)
            except BlockingIOError:
                return 0
            except OSError as exc:
                raise serial.SerialException(f"write failed: {exc}") from None
        return self._toggle.write(super().write, data)  # type: ignore[misc,no-any-return]


class _Base:
    """An ``OwnPort``'s pyserial class's own ``read`` and ``in_waiting`` (for its pump)."""

    def __init__(self, port: OwnPort) -> None:
        self._port = port
        self.read = super(OwnPort, port).read  # type: ignore[misc]
        self.timeout = port.timeout

    @property
    def in_waiting(self) -> int:
        return super(OwnPort, self._port).in_waiting  # type: ignore[misc,no-any-return]


class Serial(OwnPort, serial.Serial):  # type: ignore[misc]  # pyserial ships no type hints
    """rtupoll's port on a device (``/dev/ttyUSB0``, ``COM3``): ``OwnPort`` over the
    platform's pyserial class."""


def own_class(url: str, slot: Slot | None) -> type[OwnPort]:
    """The class rtupoll opens ``url`` with: ``Serial`` for a device, ``OwnPort`` over the
    URL's own pyserial class for ``rfc2217://``, ``socket://``, ...; bound to ``slot``."""
    base: type = serial.Serial
    if "://" in url:
        base = type(serial.serial_for_url(url, do_not_open=True))
    if base is serial.Serial:
        return Serial if slot is None else type("Serial", (Serial,), {"slot": slot})
    return type("Serial", (OwnPort, base), {"slot": slot})


def serial_class_for_url(url: str) -> tuple[str, type[OwnPort]]:
    """pyserial's handler hook: ``nodtr:///dev/ttyUSB0`` -> (``/dev/ttyUSB0``, Serial);
    ``rtupoll://N/PORT`` -> (``PORT``, rtupoll's class for it bound to slot N): PORT a
    device (``/dev/ttyUSB0``, ``COM3``) or a URL (``rfc2217://HOST:PORT``)."""
    low = url.lower()
    if low.startswith(_PREFIX):
        return url[len(_PREFIX):], Serial
    if low.startswith(_OWN_PREFIX):
        number, _, path = url[len(_OWN_PREFIX):].partition("/")
        slot = _SLOTS.get(int(number)) if number.isdigit() else None
        if slot is not None:
            return path, own_class(path, slot)
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
    ``Serial`` object: ``rtupoll://N/PORT`` for a device (``/dev/ttyUSB0``, ``COM3``, and
    ``nodtr://``'s) and for pyserial's network ports (``rfc2217://``, ``socket://``, whose
    modem lines are the server's: DTR is left as it is); other URLs pass unchanged, with
    no slot. ``parity``: the line's (a pty opened without it is marked with it,
    ``pty_parity``)."""
    if port.lower().startswith(_PREFIX):
        port, deassert_dtr = port[len(_PREFIX):], True
    network = port.lower().startswith(NETWORK)
    if ("://" in port and not network) or (network and rs485 is not None):
        if rs485 is not None:
            raise UsageError(f"{port}: --rs485 drives a serial port's RTS line; this is not "
                             "a serial port")
        return port_url(port, deassert_dtr=deassert_dtr), None
    number = next(_slot_ids)
    slot = Slot(deassert_dtr=deassert_dtr and not network, rs485=rs485, parity=parity)
    _SLOTS[number] = slot
    return f"{_OWN_PREFIX}{number}/{port}", slot


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
        return port[len(_OWN_PREFIX):].partition("/")[2]
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


def diagnose_serial(url: str, **settings: Any) -> str | None:
    """Try to open ``url`` the way pymodbus does; why it fails, or None if it opens.

    Used only after a failed open, to name the reason (pymodbus swallows it).
    """
    from rtupoll.io.port_errors import open_error

    try:
        port = serial.serial_for_url(url, exclusive=True, **settings)
    except (OSError, ValueError) as exc:
        return open_error(device_path(url), exc)
    port.close()
    return None


async def diagnose_gateway(host: str, port: int, timeout: float) -> str | None:
    """Try a plain TCP connection; why it fails, or None if it connects."""
    import asyncio

    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    except (TimeoutError, OSError) as exc:
        from rtupoll.io.port_errors import gateway_error

        return gateway_error(host, port, exc, timeout)
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return None


register()
