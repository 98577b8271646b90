"""One bus's port and line settings: the port's name, the framing, DTR, an echoing
adapter, RS-485 direction control and the idle gap. Both drivers take them
(``rtupoll.io.bus.Bus``, ``rtupoll.io.syncbus.SyncBus``); pure: no port is opened."""

from __future__ import annotations

from rtupoll.frozen import frozen
from rtupoll.io.port_names import gateway
from rtupoll.rtu import Framing


@frozen
class Rs485:
    """Direction control for a transceiver whose DE/RE pin is on RTS: RTS is raised
    ``before`` seconds before a frame's first bit and dropped ``after`` seconds after
    its last. The kernel's RS-485 mode (TIOCSRS485, pyserial's ``rs485_mode``) does it
    where the driver has it; else rtupoll toggles RTS around each write
    (``rtupoll.io.rs485``)."""

    before: float = 0.0
    after: float = 0.0


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
