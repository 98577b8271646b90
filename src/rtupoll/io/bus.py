"""One RS-485 bus: a pymodbus client per port, and the bus discipline pymodbus leaves to us.

The only module that imports pymodbus (it renames things between minor releases).
pymodbus is a good transport, but on a shared RTU line it needs help (design.md):

- **One transaction in flight**: the bus's own lock spans silence, request, reply
  and retries, so devices polled from several tasks never interleave on the wire.
- **Silence**: each request waits 3.5 character times (``Framing.silence``) after the
  last byte received and after the previous request left the wire (pymodbus alone
  sends ~0.6 ms after a reply). asyncio times in whole milliseconds, so the last
  fraction of a millisecond is slept with ``time.sleep`` (at most 1 ms, no CPU).
- **Timeout and retries per transaction**: pymodbus runs with retries=0 and a long
  backstop; the bus bounds each attempt (``asyncio.timeout``, plus the frames' wire
  time so slow baud rates do not eat the device's time) and retries itself.
- **Drain**: RTU has no transaction id, so a late reply looks exactly like the answer
  to the next request. After a timeout, the next *different* request waits until the
  line has been quiet for the drain period (default: the timeout that expired), and
  bytes arriving while no reply is awaited never reach pymodbus. A retry of the same
  request needs no drain: a late answer to attempt 1 is a right answer to attempt 2.
- **Resynchronisation**: pymodbus's RTU framer drops its whole buffer on one stray
  byte (0x00/0xFF as RS-485 transceivers switch) and loses the right reply when a
  wrong-id reply comes with it. Rather than replace the framer, received bytes are
  filtered through pymodbus's public ``trace_packet`` hook (which may rewrite the
  stream): the request's own bytes, seen on the way out, say what the answer must
  start with (``rtupoll.rtu.match``), and the filter hands pymodbus only the first
  CRC-valid frame that answers it, or nothing yet. Noise, foreign and late frames
  never reach the framer. An attempt that ends unanswered is ``diagnose``d: a bad
  CRC, truncated, mismatched or garbled reply is a ``FrameError``; silence, line
  noise or other units' frames a ``DeviceTimeout``.
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
import sys
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusIOException
from pymodbus.framer import FramerType

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
from rtupoll.rtu.match import Expect, diagnose, expect_for, find_reply

__all__ = ["OUTCOMES", "Bus", "BusStats", "PortSettings", "pymodbus_logging"]

_TICK = 0.001  # the event loop's timer resolution (epoll waits in whole milliseconds)
_DRAIN_LIMIT = 3  # at most this many drain periods after a timeout, even on a busy line
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
    unsolicited: int = 0  # bursts of bytes that answered nothing (noise, late or foreign replies)

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
        self._drain, self._connect_timeout = drain, connect_timeout
        self._broadcast_turnaround = broadcast_turnaround
        self._lock = asyncio.Lock()
        self._client: Any = None
        self._expect: Expect | None = None  # the reply awaited right now
        self._sent: Expect | None = None  # the reply the current attempt asked for
        self._rx = b""  # bytes received during the current attempt
        self._rx_at = self._tx_end = self._timeout_at = 0.0
        self._drain_for = 0.0  # >0: the line must be quiet this long before the next request
        self._idle_rx = False

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
            self._rx_at = time.monotonic()  # a fresh port: count the silence from now
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
            unit, table.read_function, timeout, retries,
            frames=8 + 5 + (2 * count if table.is_register else (count + 7) // 8))
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

        echoed = await self._transact(call, unit, function, timeout,
                                      retries if reply == "echo" else 0,
                                      frames=(8 if function == 6 else 9 + 2 * len(vals)) + 8,
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
            unit, 5, timeout, retries, frames=16)

    # -- one transaction -----------------------------------------------------

    async def _transact(self, call: Callable[[], Awaitable[Any]], unit: int, function: int,
                        timeout: float, retries: int, *, frames: int,
                        tolerate: bool = False) -> Any:
        """One transaction under the lock; ``frames``: request + normal reply bytes, whose
        wire time is added to ``timeout`` (the device's own time to answer)."""
        if not 0 < timeout <= 60 or retries < 0:
            raise UsageError(f"timeout {timeout} s / retries {retries} make no sense")
        async with self._lock:
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
            try:
                pdu = await self._attempt(call, limit)
            except (asyncio.TimeoutError, ModbusIOException):
                self._drain_for = self._drain if self._drain is not None else timeout
                self._timeout_at = time.monotonic()
                if not self.connected:
                    raise PortError(f"{self.settings.port} went away during the "
                                    f"transaction") from None
                tries = f" ({attempt + 1} tries)" if attempt else ""
                why = diagnose(self._rx, self._sent)
                failure = FrameError(f"unit {unit}, {what}: {why}{tries}") if why else \
                    DeviceTimeout(f"no reply from unit {unit} to {what} within {timeout:g} s"
                                  f"{tries}" + (f" (ignored: {self._rx[:16].hex(' ')})"
                                                if self._rx else ""))
                continue
            except ConnectionException:
                raise PortError(f"{self.settings.port} is not open") from None
            except Exception as exc:  # anything pymodbus raises: never let it escape
                raise FrameError(f"unit {unit}, {what}: {type(exc).__name__}: {exc}") from None
            if pdu is None:  # broadcast: nobody answers
                self._tx_end += self._broadcast_turnaround
                return None
            if pdu.isError():
                raise DeviceException(int(pdu.exception_code), unit=unit, function=function)
            return pdu
        raise failure

    async def _attempt(self, call: Callable[[], Awaitable[Any]], limit: float) -> Any:
        self._rx, self._sent = b"", None
        try:
            pending = call()  # may raise at once (not connected): then nothing was sent
            if sys.version_info >= (3, 11):
                async with asyncio.timeout(limit):
                    return await pending
            return await asyncio.wait_for(pending, limit)
        finally:
            self._expect = None
            if self._sent:
                self.stats.wire += self.framing.wire_time(
                    self._sent.request + (self._sent.length if self._rx else 0))

    async def _quiet_line(self, *, drain: bool) -> None:
        """Wait for the inter-frame silence, and after a timeout for a quiet line."""
        while True:
            ready = max(self._rx_at, self._tx_end) + self.framing.silence
            if drain and self._drain_for:
                quiet = max(self._rx_at, self._timeout_at) + self._drain_for
                # a line that is never quiet (a chattering device, another master) must not
                # hold the bus for ever: after a few drain periods go ahead anyway; the
                # reply filter still drops whatever is not this request's answer
                ready = max(ready, min(quiet, self._timeout_at + _DRAIN_LIMIT * self._drain_for))
            delay = ready - time.monotonic()
            if delay <= 0:
                break
            if delay > _TICK:  # whole ticks: asyncio rounds its timeouts up to the millisecond
                await asyncio.sleep(delay // _TICK * _TICK)
            else:  # the last fraction of a tick, which asyncio would overshoot by up to 1 ms
                time.sleep(delay)
        if drain:
            self._drain_for = 0.0
        if self._idle_rx:
            self.stats.unsolicited += 1
            self._idle_rx = False

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus's packet hook: timestamps both ways, and the receive-side filter.

        pymodbus passes everything received since its last send (it keeps what the
        framer did not use), so the filter sees the whole attempt each time.
        """
        now = time.monotonic()
        if sending:
            self._tx_end = now + self.framing.wire_time(len(data))
            self._expect = self._sent = expect_for(data)
            return data
        self._rx_at = now
        exp = self._expect
        if exp is None:  # nobody asked: noise, a late reply; pymodbus drops it at the next send
            self._idle_rx = True
            return b""
        self._rx = data
        frame = find_reply(data, exp)
        if frame is None:
            return b""
        self._expect = None
        return frame


def _check_unit(unit: int, *, broadcast: bool) -> None:
    if not (0 if broadcast else 1) <= unit <= 255:
        what = "0..255 (0: broadcast)" if broadcast else "1..255 (a read cannot be broadcast)"
        raise RefusedError(f"unit {unit} is outside {what}")

