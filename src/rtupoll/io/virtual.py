"""A bus with no port: the simulator's engine called directly, in-process, no thread.

For the tests whose subject is polling, scanning or writing rather than the port:
frames are built and parsed by ``rtupoll.rtu``, every rule of the line is
``rtupoll.rtu.line.Line``'s (as on the real bus), and the engine's replies arrive
after their turnaround and fault delay. Time is whatever ``clock`` says and passes
by ``sleep``: the real clock by default, or a virtual one, so a test of a device
that times out costs no wall-clock time. Late replies stay pending and reach the
line when their time comes, exactly as bytes would.
"""

from __future__ import annotations

import asyncio
import heapq
import time
from collections.abc import Awaitable, Callable, Sequence

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError, RefusedError
from rtupoll.io.interface import LineEvidence
from rtupoll.rtu import FUNCTION_NAMES, Framing, Table, read_request
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.functions import (
    answer_length,
    reply_values,
    write_coil_request,
    write_multiple_request,
    write_single_request,
)
from rtupoll.rtu.line import Answer, Garbled, Line
from rtupoll.sim.engine import Engine


class VirtualClock:
    """Time that passes only when slept through: ``clock()`` and ``await clock.sleep(s)``
    for a ``VirtualBus`` (and a scheduler's ``clock=``), so a test of timeouts and
    backoff costs no wall-clock time."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    async def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)
        await asyncio.sleep(0)  # let other tasks run, as a real sleep would


class VirtualBus(LineEvidence):
    """``BusLike`` over a simulator ``Engine``; ``clock``/``sleep`` may be virtual."""

    def __init__(self, engine: Engine, framing: Framing | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep) -> None:
        self.engine = engine
        self.framing = framing or Framing(115200)
        self.line = Line(self.framing)
        self.sent: list[bytes] = []  # every request put on the line, for tests
        self._clock, self._sleep = clock, sleep
        self._pending: list[tuple[float, int, bytes]] = []  # (arrival, seq, bytes)
        self._seq = 0
        self._lock = asyncio.Lock()

    async def open(self) -> None:
        return None

    async def close(self) -> None:
        return None

    adapter_latency = 0.0  # no USB adapter between the master and this bus

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0) -> tuple[int, ...]:
        if not 1 <= unit <= 255:
            raise RefusedError(f"unit {unit} is outside 1..255 (a read cannot be broadcast)")
        frame = await self._exchange(read_request(unit, table, address, count), timeout,
                                     retries)
        assert frame is not None
        return reply_values(frame, count)

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        vals = [int(v) for v in values]
        request = write_single_request(unit, address, vals[0]) if function == 6 else \
            write_multiple_request(unit, address, vals)
        try:
            echo = await self._exchange(request, timeout, retries if reply == "echo" else 0)
        except (DeviceTimeout, FrameError):
            if reply == "echo":
                raise
            return False
        return echo is not None

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None:
        await self._exchange(write_coil_request(unit, address, on), timeout, retries)

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0) -> bytes:
        try:
            frame = await self._exchange(with_crc(bytes((unit,)) + pdu), timeout, retries)
        except DeviceException as exc:
            return bytes((pdu[0] | 0x80, exc.code))
        return b"" if frame is None else frame[1:-2]

    # -- the line ------------------------------------------------------------------

    async def _exchange(self, request: bytes, timeout: float, retries: int) -> bytes | None:
        """One transaction: the answer frame (None for a broadcast); bus errors raised."""
        unit, function = request[0], request[1]
        what = FUNCTION_NAMES.get(function, f"function {function}")
        async with self._lock:
            await self._until(lambda: self.line.hazard_until(request, self._clock()))
            failure: Exception = DeviceTimeout(f"no reply from unit {unit}")
            sending = self.framing.wire_time(len(request))
            wire = sending + self.framing.wire_time(answer_length(request) or 0)
            for attempt in range(retries + 1):
                await self._until(self.line.ready_at if attempt == 0 else self._no_drain)
                now = self._clock()
                self.line.send(request, now)
                self.sent.append(request)
                for tx in self.engine.handle(request, now):
                    at = now + sending + tx.turnaround + \
                        tx.delay + self.framing.wire_time(len(tx.data))
                    self._seq += 1
                    heapq.heappush(self._pending, (at, self._seq, tx.data))
                if unit == 0:
                    return None
                deadline = now + timeout + wire
                while self._pending and self._pending[0][0] <= deadline:
                    at, _, data = heapq.heappop(self._pending)
                    await self._advance(at)
                    event = self.line.receive(data, at)
                    if isinstance(event, Answer):
                        if event.frame[1] & 0x80:
                            raise DeviceException(event.frame[2], unit=unit, function=function)
                        return event.frame
                    if isinstance(event, Garbled):
                        failure = FrameError(f"unit {unit}, {what}: {event.why}")
                        break
                else:
                    await self._advance(deadline)
                    why = self.line.expire(deadline, timeout)
                    failure = FrameError(f"unit {unit}, {what}: {why}") if why else \
                        DeviceTimeout(f"no reply from unit {unit} to {what} within "
                                      f"{timeout:g} s")
            raise failure

    def _no_drain(self) -> float:
        return self.line.ready_at(drain=False)

    async def _until(self, ready: Callable[[], float]) -> None:
        """Let time pass until ``ready()``, delivering replies that arrive meanwhile
        (and those already due: they reached the line before anything is sent)."""
        self._deliver_due()
        while (at := ready()) > self._clock():
            nxt = self._pending[0][0] if self._pending else at
            await self._advance(min(at, nxt))
            self._deliver_due()

    def _deliver_due(self) -> None:
        while self._pending and self._pending[0][0] <= self._clock():
            when, _, data = heapq.heappop(self._pending)
            self.line.receive(data, when)

    async def _advance(self, to: float) -> None:
        delay = to - self._clock()
        if delay > 0:
            await self._sleep(delay)
