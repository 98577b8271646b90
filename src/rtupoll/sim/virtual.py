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
import math
import time
from collections.abc import Awaitable, Callable

from rtupoll.io.interface import LineBus
from rtupoll.rtu import Framing
from rtupoll.rtu.line import Line
from rtupoll.rtu.transaction import Await, BusStats, Done, Send, Transaction
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


class VirtualBus(LineBus):
    """``BusLike`` over a simulator ``Engine``; ``clock``/``sleep`` may be virtual."""

    def __init__(self, engine: Engine, framing: Framing | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
                 echo: bool = False, idle_gap: float = 0.0) -> None:
        """``echo``: behind an adapter that echoes each request (and the line expects it);
        ``idle_gap``: the line's (``Line.idle_gap``)."""
        self.engine = engine
        self.framing = framing or Framing(115200)
        self.line = Line(self.framing, echo=echo, idle_gap=idle_gap)
        self.echo = echo
        self.stats = BusStats()
        self.sent: list[bytes] = []  # every request put on the line, for tests
        self._clock, self._sleep = clock, sleep
        self._pending: list[tuple[float, int, bytes]] = []  # (arrival, seq, bytes)
        self._seq = 0
        self._lock = asyncio.Lock()
        self._last_byte = -math.inf  # when the last byte on the line ended (either way)

    async def open(self) -> None:
        return None

    async def close(self) -> None:
        return None

    # -- the line: rtu.transaction says what, this lets virtual time pass -----------

    async def _run(self, tx: Transaction) -> Done:
        async with self._lock:
            await self._until(lambda: tx.hazard_until(self._clock()))
            started = self._clock()
            try:
                return await self._drive(tx)
            finally:
                self.stats.add(tx, self._clock() - started)

    async def _step(self, tx: Transaction, step: Send | Await) -> None:
        if isinstance(step, Await):
            await self._await(tx, step.until)
        else:
            await self._until(tx.ready_at)
            self._send(tx, self._clock())

    def _send(self, tx: Transaction, now: float) -> None:
        """The request goes at ``now``; the engine's replies reach the line when their
        turnaround, fault delay and wire time have passed."""
        tx.sent(now)
        self.sent.append(tx.request)
        sending = self.framing.wire_time(len(tx.request))
        idle, self._last_byte = now - self._last_byte, max(self._last_byte, now + sending)
        if self.echo:  # the adapter hands the request back as it goes out
            self._seq += 1
            heapq.heappush(self._pending, (now + sending, self._seq, tx.request))
        for reply in self.engine.handle(tx.request, now, idle):
            at = now + sending + reply.turnaround + reply.delay + \
                self.framing.wire_time(len(reply.data))
            self._seq += 1
            heapq.heappush(self._pending, (at, self._seq, reply.data))

    async def _await(self, tx: Transaction, until: float) -> None:
        """Deliver what arrives until the attempt is over or ``until`` passes."""
        while self._pending and self._pending[0][0] <= until:
            at, _, data = heapq.heappop(self._pending)
            self._last_byte = max(self._last_byte, at)
            await self._advance(at)
            if tx.received(data, at):
                return
        await self._advance(until)
        tx.expired(until)

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
            self._last_byte = max(self._last_byte, when)
            self.line.receive(data, when)

    async def _advance(self, to: float) -> None:
        delay = to - self._clock()
        if delay > 0:
            await self._sleep(delay)
