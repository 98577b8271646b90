"""rtupoll's own serial port: the ``rtupoll://`` and ``nodtr://`` pyserial URL handlers,
the class they build (``OwnPort``, ``Serial``) and the slots that hand a bus its port.

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
applied on open (``rtupoll.io.rs485.direction_control``: the kernel's RS-485 mode,
TIOCSRS485, where the driver has it, else ``RtsToggle`` around each write; a port with
neither is a one-line error). ``nodtr://PATH`` stays a port name users may give
(``rtupoll.io.port_names``).

Naming. pyserial finds a scheme ``X`` by importing ``<package>.protocol_X`` for
each package in ``serial.protocol_handler_packages``. Rather than ship a package
with a ``protocol_nodtr`` module, this module registers itself in ``sys.modules``
under ``rtupoll.io.own_port.protocol_nodtr`` and appends ``rtupoll.io.own_port`` to
that list (``register()``, idempotent, called on import). ``serial_class_for_url``
strips the scheme, so the port pyserial opens is the plain device path.
"""

from __future__ import annotations

import itertools
import os
import sys
import weakref
from typing import Any

import serial

from rtupoll.errors import UsageError
from rtupoll.frozen import mutable
from rtupoll.io.port_names import NETWORK, OWN, OWN_PREFIX, PREFIX, SCHEME, port_url
from rtupoll.io.port_settings import Rs485
from rtupoll.io.pty_parity import pty_parity
from rtupoll.io.rs485 import RtsToggle, direction_control


@mutable
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
    if low.startswith(PREFIX):
        return url[len(PREFIX):], Serial
    if low.startswith(OWN_PREFIX):
        number, _, path = url[len(OWN_PREFIX):].partition("/")
        slot = _SLOTS.get(int(number)) if number.isdigit() else None
        if slot is not None:
            return path, own_class(path, slot)
    raise serial.SerialException(f"expected a {PREFIX} URL, got {url!r}")


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
    if port.lower().startswith(PREFIX):
        port, deassert_dtr = port[len(PREFIX):], True
    network = port.lower().startswith(NETWORK)
    if ("://" in port and not network) or (network and rs485 is not None):
        if rs485 is not None:
            raise UsageError(f"{port}: --rs485 drives a serial port's RTS line; this is not "
                             "a serial port")
        return port_url(port, deassert_dtr=deassert_dtr), None
    number = next(_slot_ids)
    slot = Slot(deassert_dtr=deassert_dtr and not network, rs485=rs485, parity=parity)
    _SLOTS[number] = slot
    return f"{OWN_PREFIX}{number}/{port}", slot


def release(url: str) -> None:
    """Forget the slot of a ``claim``ed URL (its bus is closed for good)."""
    if url.lower().startswith(OWN_PREFIX):
        number = url[len(OWN_PREFIX):].partition("/")[0]
        if number.isdigit():
            _SLOTS.pop(int(number), None)


register()
