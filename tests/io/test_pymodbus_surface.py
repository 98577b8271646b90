"""Every pymodbus behaviour rtupoll relies on (docs/architecture.md, "pymodbus"), each
pinned here against the pymodbus installed, with a real port (the simulator's pty) or
a real socket. Run on the lowest and the highest pymodbus pyproject.toml allows.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

import pymodbus
import serial
from conftest import ANSWERED
from pymodbus.transport import CommParams, CommType, ModbusProtocol

from rtupoll.io import own_port
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]


class Recorder(ModbusProtocol):
    """The documented way to use pymodbus's transport: a ModbusProtocol subclass."""

    def __init__(self, params: CommParams) -> None:
        super().__init__(params, False)
        self.chunks: list[bytes] = []
        self.connected = 0

    def data_received(self, data: bytes) -> None:
        self.chunks.append(data)

    def callback_new_connection(self) -> ModbusProtocol:
        raise NotImplementedError

    def callback_connected(self) -> None:
        self.connected += 1

    def callback_disconnected(self, exc: Exception | None) -> None:
        pass

    def callback_data(self, data: bytes, addr: tuple[str, int] | None = None) -> int:
        return len(data)


def _serial_params(url: str) -> CommParams:
    return CommParams(comm_type=CommType.SERIAL, host=url, baudrate=115200, bytesize=8,
                      stopbits=1, parity="N", comm_name="t", reconnect_delay=0,
                      timeout_connect=5.0)


def test_a_serial_port_is_opened_through_pyserials_url_handlers(sim: Sim) -> None:
    """pymodbus opens a serial port with ``serial.serial_for_url(host, ...)``: rtupoll's
    own URL handler builds the ``Serial`` (its Slot holds it), every chunk that arrives
    reaches ``Protocol.data_received``, ``send`` writes through the transport, and
    ``close``/``is_active`` are as documented."""
    bus = sim("co2meter-an117@5", tick=None)
    url, slot = own_port.claim(bus.port, deassert_dtr=False)
    assert url.startswith("rtupoll://") and slot is not None

    async def go() -> tuple[bytes, bool, int]:
        proto = Recorder(_serial_params(url))
        assert await proto.connect()
        assert proto.is_active()
        assert isinstance(slot.port, own_port.Serial) and slot.port.is_open
        transport = proto.transport
        assert isinstance(transport, asyncio.WriteTransport)
        assert transport.get_write_buffer_size() == 0
        request = ReadRequest(5, 4, 1, 1).frame()
        proto.send(request)  # the public way; rtupoll writes to its Serial itself
        for _ in range(200):
            await asyncio.sleep(0.005)
            if len(b"".join(proto.chunks)) >= 7:
                break
        got = b"".join(proto.chunks)
        proto.close()
        return got, proto.is_active(), proto.connected

    got, active, connected = asyncio.run(go())
    assert got[:3] == bytes((5, 4, 2)) and len(got) == 7
    assert not active and connected == 1
    assert slot.port is not None and not slot.port.is_open  # pymodbus closed our Serial
    own_port.release(url)


def test_a_nonblocking_port_reads_only_what_waits(sim: Sim) -> None:
    """pymodbus sets the port's read and write timeouts to 0: reading what waits in
    rtupoll's Serial never blocks the event loop, and both take the one-system-call
    path (``io.own_port.Serial.read``/``write``)."""
    bus = sim("co2meter-an117@5", tick=None)
    url, slot = own_port.claim(bus.port, deassert_dtr=False)

    async def go() -> tuple[Any, bytes]:
        proto = Recorder(_serial_params(url))
        assert await proto.connect()
        assert slot is not None and slot.port is not None
        port = slot.port
        timeouts, data = (port.timeout, port.write_timeout), port.read(16)  # nothing waits
        proto.close()
        return timeouts, data

    assert asyncio.run(go()) == ((0, 0), b"")
    own_port.release(url)


def test_a_tcp_gateway_is_a_socket_transport_with_the_same_callbacks() -> None:
    """CommType.TCP: ``connect`` opens a socket, ``send`` writes to it, what arrives goes
    to ``data_received``."""
    async def go() -> list[bytes]:
        async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            writer.write(await reader.read(8))
            await writer.drain()
            writer.close()

        server = await asyncio.start_server(echo, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        proto = Recorder(CommParams(comm_type=CommType.TCP, host="127.0.0.1", port=port,
                                    comm_name="t", reconnect_delay=0, timeout_connect=5.0))
        assert await proto.connect()
        proto.send(b"\x01\x03\x00\x00\x00\x01\x84\x0a")
        for _ in range(200):
            await asyncio.sleep(0.005)
            if proto.chunks:
                break
        proto.close()
        server.close()
        await server.wait_closed()
        return proto.chunks

    assert b"".join(asyncio.run(go())) == b"\x01\x03\x00\x00\x00\x01\x84\x0a"


def test_a_port_that_will_not_open_makes_connect_false_not_an_exception() -> None:
    """``connect`` returns False for a missing port (rtupoll names the reason itself)."""
    async def go() -> bool:
        proto = Recorder(_serial_params("/dev/rtupoll-no-such-port"))
        try:
            return await proto.connect()
        except (OSError, serial.SerialException):
            return False  # some versions raise: rtupoll's Bus catches both

    assert asyncio.run(go()) is False


def test_pymodbus_logs_under_its_own_logger_silenced_by_rtupoll() -> None:
    """rtupoll quiets the ``pymodbus`` logger on import unless asked (``--debug``)."""
    import rtupoll.io.bus  # noqa: F401  (the import sets the level)

    assert logging.getLogger("pymodbus").level > logging.CRITICAL
    assert pymodbus.__version__


def test_the_bus_reads_through_all_of_it(sim: Sim) -> None:
    """End to end on the installed pymodbus: a read, a write echo, a timeout."""
    bus = sim("co2meter-an117@5", tick=None)

    async def go() -> tuple[tuple[int, ...], str]:
        async with Bus(PortSettings(bus.port, baudrate=115200)) as b:
            values = (await b.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)).values
            try:
                await b.read(9, Table.INPUT, 1, 1, timeout=0.05)
                why = ""
            except Exception as exc:
                why = type(exc).__name__
            return values, why

    values, why = asyncio.run(go())
    assert values == bus.registers(5, Table.INPUT, 1, 1) and why == "DeviceTimeout"


def test_a_serial_port_is_waited_on_by_the_loop_never_polled(sim: Sim) -> None:
    """pymodbus's ``SerialTransport.force_poll`` (True on Windows by the platform's name)
    is False once rtupoll's bus is imported: the transport then registers the port's
    ``fileno()`` with the loop's ``add_reader``, and rtupoll's port always has one (a
    tty's, or a ``waits.Pump``'s where the port has none)."""
    from pymodbus.transport.serialtransport import SerialTransport

    assert SerialTransport.force_poll is False
    bus = sim("huiwen-aq@3")
    url, slot = own_port.claim(bus.port, deassert_dtr=False)
    readers: list[int] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()
        add = loop.add_reader

        def noted(fd: Any, *args: Any) -> None:
            readers.append(fd)
            add(fd, *args)

        loop.add_reader = noted  # type: ignore[method-assign]
        proto = Recorder(_serial_params(url))
        assert await proto.connect()
        await asyncio.sleep(0)
        assert slot is not None and slot.port is not None
        assert readers == [slot.port.fileno()]
        proto.close()

    asyncio.run(main())
