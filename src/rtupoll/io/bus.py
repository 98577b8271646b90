"""One RS-485 bus: pymodbus carries the bytes, the sans-IO line discipline decides.

The only module that imports pymodbus (it renames things between minor releases),
and a thin one. pymodbus's transport opens the port (serial, ``nodtr://``, or an
RTU-over-TCP gateway), writes frames and delivers what arrives; frames are built
and parsed by ``rtupoll.rtu.functions`` (the one function table), and every rule of
the shared line -- the 3.5-character silence, the drain after a timeout, which
received bytes answer which request (resynchronisation past noise, foreign and late
frames, the late-reply accounting), garbled replies known at once -- is
``rtupoll.rtu.line.Line``'s, fed here with what went out, what came in and
``time.monotonic()``.

- **One transaction in flight**: the bus's lock spans silence, request, reply and
  retries, so devices polled from several tasks never interleave on the wire. A
  request whose answer could be confused with an earlier request's late reply waits
  (``Line.hazard_until``) *before* taking the lock: other devices go on meanwhile.
- **Silence**: each request goes at ``Line.ready_at``, after a long wait written by a
  timer callback (the waiting task is woken only by the answer). asyncio times in whole
  milliseconds and would overshoot, so the last 2 ms at most are slept with
  ``time.sleep``: no CPU, one wake-up, and the event loop held for that long (the
  3.5-character silence itself above 19200 baud, 1.75 ms). Bytes that arrived
  meanwhile are taken in before the frame goes, and the silence starts again.
- **Timeout and retries per transaction**: each attempt is bounded by the timeout
  plus the frames' wire time (slow baud rates do not eat the device's time); the
  bus retries itself.
- **Receiving**: the transport hands every byte to the line; pymodbus's client, its
  receive buffer, framer and PDU decoder are not used (they drop a buffer on one
  stray byte, and cost CPU the line has already spent).
- **DTR**: ``deassert_dtr`` opens the port as ``nodtr://`` (``rtupoll.io.serialport``).
- **Reconnect**: pymodbus's reconnect loop is off; a vanished port is reopened by the
  next transaction (``PortError`` while it is gone; the reason -- missing, busy,
  permission, refused, unreachable -- named by ``rtupoll.io.serialport``).

pymodbus's ``pymodbus`` logger is silenced on import unless the application set a
level on it (``pymodbus_logging`` turns it on).
"""
from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymodbus.transport import CommParams, CommType, ModbusProtocol

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
from rtupoll.io.interface import LineEvidence
from rtupoll.rtu import FUNCTION_NAMES, Framing, Table
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.functions import (
    answer_length,
    read_request,
    reply_values,
    request_length,
    write_coil_request,
    write_multiple_request,
    write_single_request,
)
from rtupoll.rtu.line import Answer, Line

__all__ = ["OUTCOMES", "Bus", "BusStats", "PortSettings", "pymodbus_logging"]

# a wait for the line this short (at most 1-2 ms) is slept at once: the event loop's timer
# (epoll waits in whole milliseconds) would overshoot it, and wake the process twice where
# once is enough (each wake costs about as much CPU as the transaction's own work)
_SLEEP_MAX = 0.002
_HAZARD_POLL = 0.01  # while waiting out a possible late reply, look again this often
_BACKSTOP = 60.0  # pymodbus's own timeout (it never waits for a reply: the line does)
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

    def utilisation(self, elapsed: float) -> float:
        return min(1.0, self.busy / elapsed) if elapsed > 0 else 0.0


class Bus(LineEvidence):
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
        self._port: _Port | None = None
        self.line = Line(self.framing, drain=drain)
        # a USB-serial adapter's latency timer (Linux sysfs), added to every reply's time
        self.adapter_latency = serialport.latency_timer(settings.port) or 0.0
        self._answer: asyncio.Future[bytes] | None = None  # the attempt in flight's

    @property
    def unsolicited(self) -> int:
        """Frames and bursts of bytes that answered nothing this bus asked."""
        return int(self.line.counts.unsolicited)

    # -- opening and closing -------------------------------------------------

    async def open(self) -> None:
        """Open the port; ``PortError`` says missing / busy / permission / refused."""
        async with self._lock:
            await self._connect()

    async def close(self) -> None:
        async with self._lock:
            if self._port is not None:
                self._port.close()
                self._port = None

    async def __aenter__(self) -> Bus:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        return self._port is not None and self._port.is_active()

    def _make_port(self) -> _Port:
        s = self.settings
        common: dict[str, Any] = dict(comm_name=s.port, reconnect_delay=0,
                                      timeout_connect=_BACKSTOP)
        if self._gateway:
            params = CommParams(comm_type=CommType.TCP, host=self._gateway[0],
                                port=self._gateway[1], **common)
        else:
            params = CommParams(comm_type=CommType.SERIAL, host=self._url, baudrate=s.baudrate,
                                bytesize=s.bytesize, stopbits=s.stopbits,
                                parity=serialport.line_parity(s.port, s.parity), **common)
        return _Port(params, self._received)

    async def _connect(self) -> None:
        if self.connected:
            return
        if self._port is None:
            self._port = self._make_port()
        why: str | None = None
        try:
            ok = await asyncio.wait_for(self._port.connect(), self._connect_timeout)
        except asyncio.TimeoutError as exc:
            ok = False
            if self._gateway:  # it does not answer: trying again would only wait again
                why = serialport.gateway_error(*self._gateway, exc, self._connect_timeout)
        except Exception:  # pymodbus, pyserial (ValueError: unknown URL)
            ok = False
        if ok and self.connected:
            self.line.opened(time.monotonic())  # a fresh port: count the silence from now
            return
        self._port.close()
        self._port = None
        if why is None and self._gateway:
            why = await serialport.diagnose_gateway(*self._gateway, self._connect_timeout)
        elif why is None:
            s = self.settings
            why = serialport.diagnose_serial(self._url, baudrate=s.baudrate, bytesize=s.bytesize,
                                             parity=serialport.line_parity(s.port, s.parity),
                                             stopbits=s.stopbits)
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
        frame = await self._transact(read_request(unit, table, address, count), timeout,
                                     retries)
        values = reply_values(frame, count)
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
        request = write_single_request(unit, address, vals[0]) if function == 6 else \
            write_multiple_request(unit, address, vals)
        echo = await self._transact(request, timeout, retries if reply == "echo" else 0,
                                    tolerate=reply != "echo")
        return bool(echo)

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None:
        _check_unit(unit, broadcast=True)
        if not 0 <= address <= 0xFFFF:
            raise RefusedError(f"coil address {address} is outside 0..65535")
        await self._transact(write_coil_request(unit, address, on), timeout, retries)

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0) -> bytes:
        """Any request PDU (function code and data) to ``unit``; the reply PDU, which is
        an exception PDU (function | 0x80, code) when the device answered with one.
        For a gateway passing other masters' requests through; a broadcast returns b""."""
        _check_unit(unit, broadcast=True)
        request = with_crc(bytes((unit,)) + pdu)
        if not pdu or request_length(request) != len(request):
            raise RefusedError(f"function 0x{pdu[:1].hex()} with {len(pdu) - 1} data bytes "
                               "is not a request this bus can send")
        try:
            frame = await self._transact(request, timeout, retries)
        except DeviceException as exc:
            return bytes((pdu[0] | 0x80, exc.code))
        return frame[1:-2]

    # -- one transaction -----------------------------------------------------

    async def _transact(self, request: bytes, timeout: float, retries: int, *,
                        tolerate: bool = False) -> bytes:
        """One transaction under the lock, once no earlier request's late reply could be
        mistaken for its answer: the answer frame (b"" for a broadcast, or a tolerated
        write without a valid echo). The request's and its reply's wire time is added to
        ``timeout`` (the device's own time to answer)."""
        if not 0 < timeout <= 60 or retries < 0:
            raise UsageError(f"timeout {timeout} s / retries {retries} make no sense")
        frames = len(request) + (answer_length(request) or 0)
        while True:
            await self._hazard_clear(request)  # returns at once when there is none
            await self._lock.acquire()
            now = time.monotonic()
            if self.line.hazard_until(request, now) <= now:
                break
            self._lock.release()  # another task's request made one: wait again
        started = time.monotonic()
        outcome = "ok"
        try:
            frame = await self._attempts(request, timeout, retries,
                                         timeout + self.framing.wire_time(frames))
            if not frame:
                outcome = "broadcast"
            return frame
        except (DeviceException, PortError) as exc:
            outcome = "exception" if isinstance(exc, DeviceException) else "port"
            raise
        except BusError as exc:  # DeviceTimeout or FrameError
            outcome = "unconfirmed" if tolerate else \
                "timeout" if isinstance(exc, DeviceTimeout) else "frame"
            if tolerate:
                return b""
            raise
        finally:
            self.stats.transactions += 1
            self.stats.outcomes[outcome] += 1
            self.stats.busy += time.monotonic() - started
            self._lock.release()

    async def _hazard_clear(self, request: bytes) -> None:
        """Wait (without holding the bus) until no earlier request's late reply could be
        taken for ``request``'s answer; an arriving answer ends the wait early."""
        while True:
            now = time.monotonic()
            until = self.line.hazard_until(request, now)
            if until <= now:
                return
            await asyncio.sleep(min(until - now, _HAZARD_POLL))

    async def _attempts(self, request: bytes, timeout: float, retries: int,
                        limit: float) -> bytes:
        unit, function = request[0], request[1]
        failure: BusError = DeviceTimeout(f"no reply from unit {unit}")
        what = FUNCTION_NAMES.get(function, f"function {function}")
        for attempt in range(retries + 1):
            await self._connect()
            if attempt:
                self.stats.retries += 1
            self.stats.attempts += 1
            tries = f" ({attempt + 1} tries)" if attempt else ""
            try:
                frame = await self._attempt(request, limit, drain=attempt == 0)
            except _Garbled as exc:
                failure = FrameError(f"unit {unit}, {what}: {exc}{tries}")
                continue
            except asyncio.TimeoutError:
                rx = bytes(self.line.attempt.rx) if self.line.attempt else b""
                why = self.line.expire(time.monotonic(), timeout)
                if not self.connected:
                    raise PortError(f"{self.settings.port} went away during the "
                                    f"transaction") from None
                failure = FrameError(f"unit {unit}, {what}: {why}{tries}") if why else \
                    DeviceTimeout(f"no reply from unit {unit} to {what} within {timeout:g} s"
                                  f"{tries}" + (f" (ignored: {rx[:16].hex(' ')})" if rx else ""))
                continue
            if not frame:  # broadcast: nobody answers
                self.line.after_broadcast(self._broadcast_turnaround)
                return b""
            if frame[1] & 0x80:
                raise DeviceException(frame[2], unit=unit, function=function)
            return frame
        raise failure

    async def _attempt(self, request: bytes, limit: float, *, drain: bool) -> bytes:
        """Send ``request`` once the line lets it go (``drain``: honour a drain); its
        answer frame (b"" for a broadcast), ``_Garbled`` as soon as the line knows the
        reply is garbled, ``asyncio.TimeoutError`` ``limit`` after it went out.

        The frame goes as soon as the silence is over: written here after a short sleep,
        or by a timer callback after a long wait, never by this task waking up first (a
        turn of the event loop less per transaction)."""
        if not self.connected:
            raise PortError(f"{self.settings.port} is not open")
        loop = asyncio.get_running_loop()
        answer: asyncio.Future[bytes] = loop.create_future()
        timer: asyncio.Handle | None = None

        def send() -> None:
            nonlocal timer
            delay = self.line.ready_at(drain=drain) - time.monotonic()
            if delay > _SLEEP_MAX:  # the event loop's timer, which fires up to 1 ms late,
                timer = loop.call_later(delay - _SLEEP_MAX, send)  # for all but the end
                return
            if delay > 0:
                time.sleep(delay)
                if self._took_input():  # bytes came meanwhile: the silence starts again
                    timer = loop.call_soon(send)
                    return
            if not self.connected:
                answer.set_exception(PortError(f"{self.settings.port} went away"))
                return
            try:
                self.line.send(request, time.monotonic())
                self.stats.wire += self.framing.wire_time(len(request))
                self._send(request)
            except Exception as exc:  # a callback's error would reach no one: the caller's
                answer.set_exception(exc)
                return
            if request[0] == 0:
                answer.set_result(b"")
            else:
                self._answer = answer
                timer = loop.call_later(limit, _expire, answer)

        send()
        try:
            return await answer
        finally:
            if timer is not None:
                timer.cancel()
            self._answer = None

    def _took_input(self) -> bool:
        """Whether bytes arrived while the event loop slept; they go to the line now, so
        the silence is counted from them. (Serial ports: a gateway keeps the silence on
        its own line.)"""
        transport: Any = self._port.transport if self._port is not None else None
        port = getattr(transport, "sync_serial", None)
        try:
            if port is None or not port.in_waiting:
                return False
        except Exception:  # pyserial's SerialException: the write that follows fails too
            return False
        transport.intern_read_ready()
        return True

    def _send(self, request: bytes) -> None:
        """Put ``request`` on the wire now. pymodbus's serial transport would only queue
        it for the event loop's next turn, registering and unregistering the port for
        writing each time; with nothing queued, the frame is written to its port at once
        (what does not fit the port's buffer is queued as before, and a port that fails
        is closed as pymodbus's own writer would). A socket (RTU over TCP) writes at once
        anyway."""
        assert self._port is not None  # _attempt checked
        transport: Any = self._port.transport
        port = getattr(transport, "sync_serial", None)
        if port is None or getattr(transport, "intern_write_buffer", None) != []:
            transport.write(request)
            return
        try:
            sent = port.write(request) or 0
        except Exception as exc:  # pyserial's SerialException: the port went away
            transport.close(exc=exc)
            return
        if sent < len(request):
            transport.write(request[sent:])

    def _received(self, data: bytes) -> None:
        """What the port received: every byte goes to the line."""
        event = self.line.receive(data, time.monotonic())
        waiter = self._answer
        if event is not None and waiter is not None and not waiter.done():
            if isinstance(event, Answer):
                self.stats.wire += self.framing.wire_time(len(event.frame))
                waiter.set_result(event.frame)
            else:
                waiter.set_exception(_Garbled(event.why))


class _Port(ModbusProtocol):
    """pymodbus's transport (a serial port, or a socket to a gateway) handing every
    received byte to the bus: pymodbus's receive buffer, framer and transaction manager
    are not in the way (they drop a buffer on one stray byte, and cost CPU)."""

    def __init__(self, params: CommParams, received: Callable[[bytes], None]) -> None:
        super().__init__(params, False)
        self._received = received

    def data_received(self, data: bytes) -> None:
        self._received(data)

    def callback_new_connection(self) -> ModbusProtocol:  # only servers accept connections
        raise NotImplementedError

    def callback_connected(self) -> None:
        pass

    def callback_disconnected(self, exc: Exception | None) -> None:
        pass

    def callback_data(self, data: bytes, addr: tuple[str, int] | None = None) -> int:
        return len(data)  # not called: data_received goes to the bus


def _expire(answer: asyncio.Future[bytes]) -> None:
    if not answer.done():
        answer.set_exception(asyncio.TimeoutError())


class _Garbled(Exception):
    """The line saw a complete reply with a bad CRC: retry now, not after the timeout."""


def _check_unit(unit: int, *, broadcast: bool) -> None:
    if not (0 if broadcast else 1) <= unit <= 255:
        what = "0..255 (0: broadcast)" if broadcast else "1..255 (a read cannot be broadcast)"
        raise RefusedError(f"unit {unit} is outside {what}")

