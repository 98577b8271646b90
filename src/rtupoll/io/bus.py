"""One RS-485 bus: a pymodbus client per port, driven by the sans-IO line discipline.

The only module that imports pymodbus (it renames things between minor releases),
and a thin one: pymodbus carries the bytes and builds and parses the PDUs; every rule
of the shared line -- the 3.5-character silence, the drain after a timeout, which
received bytes answer which request (resynchronisation past noise, foreign and late
frames), garbled replies known at once -- is ``rtupoll.rtu.line.Line``'s, fed here with
what went out, what came in, and ``time.monotonic()``.

- **One transaction in flight**: the bus's lock spans silence, request, reply and
  retries, so devices polled from several tasks never interleave on the wire.
- **Silence**: each request waits until ``Line.ready_at``; asyncio times in whole
  milliseconds, so the last fraction of a millisecond is slept with ``time.sleep``
  (at most 1 ms, no CPU).
- **Timeout and retries per transaction**: pymodbus runs with retries=0 and a long
  backstop; the bus bounds each attempt (the timeout plus the frames' wire time, so
  slow baud rates do not eat the device's time) and retries itself.
- **Receive filter**: received bytes pass through pymodbus's public ``trace_packet``
  hook, which may rewrite the stream: the line discipline sees every byte, and
  pymodbus is handed only the frame the line identified as the answer, or nothing.
- **DTR**: ``deassert_dtr`` opens the port as ``nodtr://`` (``rtupoll.io.serialport``).
- **Reconnect**: pymodbus's reconnect loop is off; a vanished port is reopened by the
  next transaction (``PortError`` while it is gone; the reason -- missing, busy,
  permission, refused, unreachable -- named by ``rtupoll.io.serialport``).

pymodbus exceptions never escape; its ``pymodbus`` logger is silenced on import
unless the application set a level on it (``pymodbus_logging`` turns it on).
"""
from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.framer import FramerType
from pymodbus.pdu import DecodePDU

from rtupoll.errors import (
    BusError,
    DeviceException,
    DeviceTimeout,
    FrameError,
    PortError,
    RefusedError,
    UsageError,
)
from rtupoll.io import serialport
from rtupoll.rtu import FUNCTION_NAMES, Framing, Table
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.functions import (
    answer_length,
    read_request,
    write_coil_request,
    write_multiple_request,
    write_single_request,
)
from rtupoll.rtu.line import Answer, Garbled, Line

__all__ = ["OUTCOMES", "Bus", "BusStats", "PortSettings", "pymodbus_logging"]

_TICK = 0.001  # the event loop's timer resolution (epoll waits in whole milliseconds)
_HAZARD_POLL = 0.01  # while waiting out a possible late reply, look again this often
_BACKSTOP = 60.0  # pymodbus's own timeout; the bus's per-attempt deadline is always shorter
_READERS = {Table.COIL: "read_coils", Table.DISCRETE: "read_discrete_inputs",
            Table.INPUT: "read_input_registers", Table.HOLDING: "read_holding_registers"}
_REPLY_MODES = ("echo", "none", "malformed", "any")
# BusStats.outcomes keys: one per transaction ("unconfirmed": a tolerated write without echo)
OUTCOMES = ("ok", "timeout", "frame", "exception", "port", "broadcast", "unconfirmed")

_PYMODBUS_LOG = logging.getLogger("pymodbus")
if _PYMODBUS_LOG.level == logging.NOTSET:  # quiet, unless the application asked for it
    _PYMODBUS_LOG.setLevel(logging.CRITICAL + 1)


def pymodbus_logging(level: int = logging.DEBUG) -> None:
    """Let pymodbus's own log through (``--debug``); it is silent by default."""
    _PYMODBUS_LOG.setLevel(level)


@dataclass(frozen=True)
class PortSettings:
    port: str  # "/dev/ttyUSB0", a pty path, or "tcp://HOST:PORT" (RTU over a TCP gateway)
    baudrate: int = 9600
    parity: str = "N"
    bytesize: int = 8
    stopbits: int = 1
    deassert_dtr: bool = False  # open with DTR/RTS deasserted (CO2Meter boards reset on DTR)

    @property
    def framing(self) -> Framing:
        return Framing(self.baudrate, self.bytesize, self.parity, self.stopbits)

    @property
    def gateway(self) -> tuple[str, int] | None:
        """(host, port) for ``tcp://HOST:PORT``, None for a serial port."""
        return serialport.gateway(self.port)


@dataclass
class BusStats:
    """What the bus did. ``busy`` over elapsed time is the bus's utilisation."""

    transactions: int = 0  # read/write calls completed, whatever the outcome
    attempts: int = 0  # requests put on the wire, retries included
    retries: int = 0
    busy: float = 0.0  # seconds the bus was held: silences, requests, replies, timeouts, drains
    wire: float = 0.0  # seconds of frames on the wire at the baud rate (the physical floor)
    outcomes: Counter[str] = field(default_factory=Counter)  # see OUTCOMES
    hazard_waits: int = 0  # polls spent waiting out a possible late reply (see rtu.line)

    def utilisation(self, elapsed: float) -> float:
        return min(1.0, self.busy / elapsed) if elapsed > 0 else 0.0


class Bus:
    """One port, one master, one transaction at a time. See the module docstring.

    ``drain``: quiet period required after a timeout before the next request
    (None: the length of the timeout that expired). ``broadcast_turnaround``: pause
    after a broadcast so devices can act on it before the next request.
    """

    def __init__(self, settings: PortSettings, *, drain: float | None = None,
                 connect_timeout: float = 3.0, broadcast_turnaround: float = 0.1) -> None:
        self.settings = settings
        self.framing = settings.framing
        self.stats = BusStats()
        self._gateway = settings.gateway
        self._url = serialport.port_url(settings.port, deassert_dtr=settings.deassert_dtr)
        self._connect_timeout = connect_timeout
        self._broadcast_turnaround = broadcast_turnaround
        self._lock = asyncio.Lock()
        self._client: Any = None
        self.line = Line(self.framing, drain=drain)
        # a USB-serial adapter's latency timer (Linux sysfs), added to every reply's time
        self.adapter_latency = serialport.latency_timer(settings.port) or 0.0
        self._seen = b""  # what pymodbus last showed the receive hook (it resends its buffer)
        self._answer = b""  # the frame to hand pymodbus, once the line identified it
        self._garbled: asyncio.Future[str] | None = None  # set when the line knows at once

    @property
    def unsolicited(self) -> int:
        """Frames and bursts of bytes that answered nothing this bus asked."""
        return int(self.line.counts.unsolicited)

    def late(self, unit: int) -> int:
        """Late replies from ``unit``: answers to requests that had timed out."""
        return int(self.line.counts.late[unit])

    def reply_time(self, unit: int) -> float | None:
        """``unit``'s last reply time (request's end to reply's first byte), if any."""
        return self.line.reply_time.get(unit)

    def late_reply_time(self, unit: int) -> float | None:
        """The reply time of ``unit``'s last late reply, if it sent one."""
        return self.line.late_reply_time.get(unit)

    # -- opening and closing -------------------------------------------------

    async def open(self) -> None:
        """Open the port; ``PortError`` says missing / busy / permission / refused."""
        async with self._lock:
            await self._connect()

    async def close(self) -> None:
        async with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    async def __aenter__(self) -> Bus:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        return bool(self._client and self._client.connected)

    def _make_client(self) -> Any:
        common: dict[str, Any] = dict(framer=FramerType.RTU, timeout=_BACKSTOP, retries=0,
                                      reconnect_delay=0, name=self.settings.port,
                                      trace_packet=self._trace)
        if self._gateway:
            client: Any = AsyncModbusTcpClient(self._gateway[0], port=self._gateway[1],
                                               **common)
        else:
            s = self.settings
            client = AsyncModbusSerialClient(self._url, baudrate=s.baudrate, bytesize=s.bytesize,
                                             parity=s.parity, stopbits=s.stopbits, **common)
        client.set_max_no_responses(1 << 30)  # never let pymodbus drop the link on timeouts
        return client

    async def _connect(self) -> None:
        if self.connected:
            return
        if self._client is None:
            self._client = self._make_client()
        why: str | None = None
        try:
            ok = await asyncio.wait_for(self._client.connect(), self._connect_timeout)
        except asyncio.TimeoutError as exc:
            ok = False
            if self._gateway:  # it does not answer: trying again would only wait again
                why = serialport.gateway_error(*self._gateway, exc, self._connect_timeout)
        except Exception:  # pymodbus, pyserial (ValueError: unknown URL)
            ok = False
        if ok and self.connected:
            self.line.opened(time.monotonic())  # a fresh port: count the silence from now
            return
        self._client.close()
        self._client = None
        if why is None and self._gateway:
            why = await serialport.diagnose_gateway(*self._gateway, self._connect_timeout)
        elif why is None:
            s = self.settings
            why = serialport.diagnose_serial(self._url, baudrate=s.baudrate, bytesize=s.bytesize,
                                             parity=s.parity, stopbits=s.stopbits)
        raise PortError(why or f"cannot open {self.settings.port} (it opens now: retry)")

    # -- the public transactions ---------------------------------------------

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0) -> tuple[int, ...]:
        """Registers as 16-bit ints; coils and discrete inputs as 0/1."""
        _check_unit(unit, broadcast=False)
        most = 125 if table.is_register else 2000
        if not 1 <= count <= most or not address >= 0 or address + count > 0x10000:
            raise RefusedError(f"cannot read {count} {table.value} from 0x{address:X} "
                               f"(1..{most} within 0..65535)")
        method = _READERS[table]
        pdu = await self._transact(
            lambda: getattr(self._client, method)(address, count=count, device_id=unit),
            read_request(unit, table, address, count), timeout, retries)
        values = tuple(int(v) for v in pdu.registers) if table.is_register else \
            tuple(int(b) for b in pdu.bits[:count])
        if len(values) != count:
            raise FrameError(f"unit {unit} returned {len(values)} values for {count}")
        return values

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        """Function 6 (one value) or 16; True when the device confirmed it with an echo.

        With ``reply`` other than "echo" a missing or malformed reply is not an error and
        the write is not repeated (False): the caller verifies by reading back. An
        exception reply is always an error."""
        _check_unit(unit, broadcast=True)
        if reply not in _REPLY_MODES:
            raise UsageError(f"reply {reply!r} is not one of: {', '.join(_REPLY_MODES)}")
        vals = [int(v) for v in values]
        if function not in (6, 16) or (function == 6 and len(vals) != 1) or \
                not 1 <= len(vals) <= 123 or address < 0 or address + len(vals) > 0x10000 or \
                any(not 0 <= v <= 0xFFFF for v in vals):
            raise RefusedError(f"cannot write {vals} at 0x{address:X} with function {function}")

        def call() -> Awaitable[Any]:  # looked up per attempt: a reconnect replaces the client
            if function == 6:
                return self._client.write_register(  # type: ignore[no-any-return]
                    address, vals[0], device_id=unit, no_response_expected=unit == 0)
            return self._client.write_registers(  # type: ignore[no-any-return]
                address, vals, device_id=unit, no_response_expected=unit == 0)

        request = write_single_request(unit, address, vals[0]) if function == 6 else \
            write_multiple_request(unit, address, vals)
        echoed = await self._transact(call, request, timeout, retries if reply == "echo" else 0,
                                      tolerate=reply != "echo")
        return echoed is not None

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None:
        _check_unit(unit, broadcast=True)
        if not 0 <= address <= 0xFFFF:
            raise RefusedError(f"coil address {address} is outside 0..65535")
        await self._transact(
            lambda: self._client.write_coil(address, bool(on), device_id=unit,
                                            no_response_expected=unit == 0),
            write_coil_request(unit, address, on), timeout, retries)

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0) -> bytes:
        """Any request PDU (function code and data) to ``unit``; the reply PDU, which is
        an exception PDU (function | 0x80, code) when the device answered with one.
        For a gateway passing other masters' requests through; a broadcast returns b""."""
        _check_unit(unit, broadcast=True)
        try:
            request = DecodePDU(True).decode(pdu)
        except Exception:  # pymodbus's decoder raises several kinds on bad input
            request = None
        if request is None:
            raise RefusedError(f"function 0x{pdu[:1].hex()} with {len(pdu) - 1} data bytes "
                               "is not a request this bus can send")
        request.dev_id = unit
        frame = with_crc(bytes((unit,)) + pdu)
        try:
            reply = await self._transact(
                lambda: self._client.execute(unit == 0, request), frame, timeout, retries)
        except DeviceException as exc:
            return bytes((pdu[0] | 0x80, exc.code))
        return b"" if reply is None else bytes((reply.function_code,)) + reply.encode()

    # -- one transaction -----------------------------------------------------

    async def _transact(self, call: Callable[[], Awaitable[Any]], request: bytes,
                        timeout: float, retries: int, *, tolerate: bool = False) -> Any:
        """One transaction (``request``: the frame pymodbus will send) under the lock,
        once no earlier request's late reply could be mistaken for its answer. The
        request's and its reply's wire time is added to ``timeout`` (the device's own
        time to answer)."""
        if not 0 < timeout <= 60 or retries < 0:
            raise UsageError(f"timeout {timeout} s / retries {retries} make no sense")
        unit, function = request[0], request[1]
        frames = len(request) + (answer_length(request) or 0)
        while True:
            await self._hazard_clear(request)
            await self._lock.acquire()
            if self.line.hazard_until(request, time.monotonic()) <= time.monotonic():
                break
            self._lock.release()  # another task's request made one: wait again
        try:
            started = time.monotonic()
            outcome = "ok"
            try:
                result = await self._attempts(call, unit, function, timeout, retries,
                                              timeout + self.framing.wire_time(frames))
                if result is None:
                    outcome = "broadcast"
                return result
            except (DeviceException, PortError) as exc:
                outcome = "exception" if isinstance(exc, DeviceException) else "port"
                raise
            except BusError as exc:  # DeviceTimeout or FrameError
                outcome = "unconfirmed" if tolerate else \
                    "timeout" if isinstance(exc, DeviceTimeout) else "frame"
                if tolerate:
                    return None
                raise
            finally:
                self.stats.transactions += 1
                self.stats.outcomes[outcome] += 1
                self.stats.busy += time.monotonic() - started
        finally:
            self._lock.release()

    async def _hazard_clear(self, request: bytes) -> None:
        """Wait (without holding the bus) until no earlier request's late reply could be
        taken for ``request``'s answer; an arriving answer ends the wait early."""
        while True:
            now = time.monotonic()
            until = self.line.hazard_until(request, now)
            if until <= now:
                return
            self.stats.hazard_waits += 1
            await asyncio.sleep(min(until - now, _HAZARD_POLL))

    async def _attempts(self, call: Callable[[], Awaitable[Any]], unit: int, function: int,
                        timeout: float, retries: int, limit: float) -> Any:
        failure: BusError = DeviceTimeout(f"no reply from unit {unit}")
        what = FUNCTION_NAMES.get(function, f"function {function}")
        for attempt in range(retries + 1):
            await self._connect()
            await self._quiet_line(drain=attempt == 0)
            if attempt:
                self.stats.retries += 1
            self.stats.attempts += 1
            tries = f" ({attempt + 1} tries)" if attempt else ""
            try:
                pdu = await self._attempt(call, limit)
            except _Garbled as exc:
                failure = FrameError(f"unit {unit}, {what}: {exc}{tries}")
                continue
            except (asyncio.TimeoutError, ModbusIOException):
                rx = bytes(self.line.attempt.rx) if self.line.attempt else b""
                why = self.line.expire(time.monotonic(), timeout)
                if not self.connected:
                    raise PortError(f"{self.settings.port} went away during the "
                                    f"transaction") from None
                failure = FrameError(f"unit {unit}, {what}: {why}{tries}") if why else \
                    DeviceTimeout(f"no reply from unit {unit} to {what} within {timeout:g} s"
                                  f"{tries}" + (f" (ignored: {rx[:16].hex(' ')})" if rx else ""))
                continue
            except ConnectionException:
                self.line.abandon()
                raise PortError(f"{self.settings.port} is not open") from None
            except Exception as exc:  # anything pymodbus raises: never let it escape
                self.line.abandon()
                raise FrameError(f"unit {unit}, {what}: {type(exc).__name__}: {exc}") from None
            if pdu is None:  # broadcast: nobody answers
                self.line.after_broadcast(self._broadcast_turnaround)
                return None
            if pdu.isError():
                raise DeviceException(int(pdu.exception_code), unit=unit, function=function)
            return pdu
        raise failure

    async def _attempt(self, call: Callable[[], Awaitable[Any]], limit: float) -> Any:
        """One request and its answer; ``_Garbled`` as soon as the line knows the reply
        is garbled, ``asyncio.TimeoutError`` after ``limit`` seconds."""
        self._answer, self._seen = b"", b""
        self._garbled = asyncio.get_running_loop().create_future()
        try:
            pending = asyncio.ensure_future(call())  # raises at once if not connected
            done, _ = await asyncio.wait((pending, self._garbled), timeout=limit,
                                         return_when=asyncio.FIRST_COMPLETED)
            if pending in done:
                return pending.result()
            pending.cancel()
            await asyncio.gather(pending, return_exceptions=True)
            if self._garbled in done:
                raise _Garbled(self._garbled.result())
            raise asyncio.TimeoutError
        finally:
            self._garbled = None

    async def _quiet_line(self, *, drain: bool) -> None:
        """Wait until the line discipline lets the next frame go."""
        while True:
            delay = self.line.ready_at(drain=drain) - time.monotonic()
            if delay <= 0:
                break
            if delay > _TICK:  # whole ticks: asyncio rounds its timeouts up to the millisecond
                await asyncio.sleep(delay // _TICK * _TICK)
            else:  # the last fraction of a tick, which asyncio would overshoot by up to 1 ms
                time.sleep(delay)

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus's packet hook: what goes out and what comes in, through the line.

        pymodbus passes everything received since its last send (it keeps what its
        framer did not use), so only what is new since the last call is fed on.
        """
        now = time.monotonic()
        if sending:
            self.line.send(data, now)
            self.stats.wire += self.framing.wire_time(len(data))
            self._seen = b""
            return data
        new = _new_bytes(self._seen, data)
        self._seen = data
        event = self.line.receive(new, now)
        if isinstance(event, Answer):
            self._answer = event.frame
            self.stats.wire += self.framing.wire_time(len(event.frame))
            self._seen = data[len(event.frame):]  # pymodbus cuts what its framer used
            return self._answer
        if isinstance(event, Garbled) and self._garbled is not None \
                and not self._garbled.done():
            self._garbled.set_result(event.why)
        return b""


class _Garbled(Exception):
    """The line saw a complete reply with a bad CRC: retry now, not after the timeout."""


def _new_bytes(seen: bytes, data: bytes) -> bytes:
    """What ``data`` (pymodbus's receive buffer) holds beyond ``seen`` (the last one),
    allowing for a cut from its front."""
    if data.startswith(seen):
        return data[len(seen):]
    for k in range(1, len(seen) + 1):
        if data.startswith(seen[k:]):
            return data[len(seen) - k:]
    return data


def _check_unit(unit: int, *, broadcast: bool) -> None:
    if not (0 if broadcast else 1) <= unit <= 255:
        what = "0..255 (0: broadcast)" if broadcast else "1..255 (a read cannot be broadcast)"
        raise RefusedError(f"unit {unit} is outside {what}")

