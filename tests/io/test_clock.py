"""The line's clock (``rtupoll.io.clock``), proven in virtual time: with a monotonic clock
that ticks every 15.6 ms (Windows before Python 3.13), a request sent by the real
``SyncBus`` goes inside the 3.5-character silence after a reply; with the clock
``choose`` picks for that resolution, it does not.

The bus is the real ``SyncBus`` (its wait: the portable ``PortWait``, as on a Windows
COM port) on a virtual port over the simulator's engine: a request written to it is
answered by the engine, the reply's bytes arriving at once (as a USB adapter hands a
frame over) when the device's turnaround has passed. Time passes only in the virtual
clock: the port's waits and the bus's sleeps move it, and so does the bus's own work
between two readings of its clock (``COST``: a few microseconds of Python, which is all
a coarse clock needs to tick in between).

The async ``Bus`` is run for real on an event loop whose clock ticks every 15.6 ms, as
asyncio's does there: its timers, set by delays and set again when one runs early,
never end an attempt before its deadline, and the loop does not spin.
"""

from __future__ import annotations

import asyncio
import io
import math
import time
from collections.abc import Callable

import pytest
from virtual import START

from rtupoll.errors import DeviceTimeout
from rtupoll.io import clock, waits
from rtupoll.io.bus import Bus
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus, run
from rtupoll.rtu import Framing, Table
from rtupoll.sim.engine import Engine
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import build

TICK = 0.015625  # GetTickCount64's 15.6 ms: time.monotonic on Windows before Python 3.13
COST = 20e-6  # seconds of the bus's own work between two readings of its clock
BAUD = 9600
SILENCE = Framing(BAUD).silence  # 3.5 characters: 4.0 ms


class Virtual:
    """True time, and the clocks a bus may read of it."""

    def __init__(self) -> None:
        self.now = START

    def sleep(self, seconds: float) -> None:
        self.now += max(0.0, seconds)

    def fine(self) -> float:  # time.perf_counter (or a fine monotonic): true time
        self.now += COST
        return self.now

    def coarse(self) -> float:  # time.monotonic at 15.6 ms
        self.now += COST
        return math.floor(self.now / TICK) * TICK


class VirtualPort:
    """pyserial's API as ``PortWait`` uses it (no descriptor: ``fileno`` unsupported, as
    on Windows) over the simulator's engine; ``sent``: (true time, frame) of each write,
    ``heard``: (true time, bytes) of each reply put on the line."""

    def __init__(self, time: Virtual, turnaround: float) -> None:
        config = build(["huiwen-aq@3"], tick=None)
        self.engine = Engine(config.devices, config.faults, seed=1, tick=None)
        self.time, self.turnaround = time, turnaround
        self.timeout: float | None = waits.SLICE
        self.is_open = True
        self.sent: list[tuple[float, bytes]] = []
        self.heard: list[tuple[float, bytes]] = []
        self._arriving: list[tuple[float, bytes]] = []

    def fileno(self) -> int:
        raise io.UnsupportedOperation("fileno")

    def write(self, frame: bytes) -> int:
        now = self.time.now
        self.sent.append((now, frame))
        end = now + Framing(BAUD).wire_time(len(frame))
        for reply in self.engine.handle(frame, now):
            # the reply lands whole, the turnaround after the request's last byte and
            # just before the coarse clock's next tick (the worst case, made certain)
            at = end + self.turnaround + Framing(BAUD).wire_time(len(reply.data))
            at = math.ceil(at / TICK) * TICK - 1.5 * COST
            self._arriving.append((at, reply.data))
            self.heard.append((at, reply.data))
        return len(frame)

    @property
    def in_waiting(self) -> int:
        return sum(len(d) for at, d in self._arriving if at <= self.time.now)

    def read(self, size: int = 1) -> bytes:
        if not self.in_waiting and self._arriving and self.timeout:
            self.time.now = min(self._arriving[0][0], self.time.now + self.timeout)
        elif not self.in_waiting and self.timeout:
            self.time.now += self.timeout
        data = b"".join(d for at, d in self._arriving if at <= self.time.now)
        self._arriving = [(at, d) for at, d in self._arriving if at > self.time.now]
        taken, rest = data[:size], data[size:]
        if rest:
            self._arriving.insert(0, (self.time.now, rest))
        return taken

    def close(self) -> None:
        self.is_open = False


def gaps(reading: str) -> list[float]:
    """Two reads in a row, the bus reading ``reading`` clock: the true time between each
    reply's last byte and the next request's first."""
    t = Virtual()
    port = VirtualPort(t, turnaround=0.001)
    if reading == "coarse":
        line_clock = t.coarse
    else:  # what choose gives for that monotonic clock: perf_counter, fine (true time)
        assert clock.choose(TICK) is time.perf_counter
        line_clock = t.fine
    bus = SyncBus(PortSettings("COM5", baudrate=BAUD), clock=line_clock, sleep=t.sleep,
                  opened=port)
    with bus:
        for _ in range(3):
            run(bus.read(3, Table.INPUT, 30008, 1, timeout=0.2))  # each answered
    return [sent - heard for (heard, _), (sent, _) in zip(port.heard, port.sent[1:],
                                                           strict=False)]


def test_choose_takes_perf_counter_where_monotonic_ticks_coarsely() -> None:
    assert clock.choose(TICK) is time.perf_counter  # Windows, Python 3.11 and 3.12
    assert clock.choose(1e-9) is time.monotonic  # Linux; Windows from 3.13 (100 ns)
    assert clock.choose(1e-7) is time.monotonic
    info = time.get_clock_info("monotonic")
    assert clock.now is (time.monotonic if info.resolution <= clock.FINE
                         else time.perf_counter)


def test_a_coarse_monotonic_clock_sends_inside_the_silence() -> None:
    """The old way: the line's times from a 15.6 ms clock. A reply stamped just before a
    tick reads, a few microseconds later, as 15.6 ms old: the next request goes at once."""
    assert min(gaps("coarse")) < SILENCE / 10


def test_the_chosen_clock_keeps_the_silence() -> None:
    got = gaps("chosen")
    assert len(got) == 2
    assert min(got) >= SILENCE


class CoarseLoop(asyncio.SelectorEventLoop):
    """An event loop whose clock ticks every 15.6 ms, as asyncio's is on Windows before
    Python 3.13 (``loop.time()`` is ``time.monotonic``, its resolution the loop's
    ``_clock_resolution``): it runs a timer up to a tick early when it wakes for
    something else. ``turns``: how often it went round (a spin would be thousands)."""

    turns = 0

    def __init__(self) -> None:
        super().__init__()
        self._clock_resolution = TICK

    def time(self) -> float:
        return math.floor(time.monotonic() / TICK) * TICK

    def _run_once(self) -> None:
        self.turns += 1
        super()._run_once()  # type: ignore[misc]


def test_the_bus_on_a_coarse_event_loop_keeps_its_deadlines_and_does_not_spin(
        sim: Callable[..., SimulatedBus]) -> None:
    """The line's times are not the loop's: the async ``Bus`` sets its timers by delays
    and sets them again when one runs early, so on a loop that ticks every 15.6 ms an
    attempt to a dead device lasts its whole timeout (never cut short by an early
    timer), the live one answers each time, and the loop does not spin meanwhile."""
    bus = sim("huiwen-aq@3", baudrate=BAUD)
    timeout = 0.1
    dead: list[float] = []
    took: list[float] = []
    # the attempt's own limit: the timeout plus both frames' wire time (8 + 7 bytes)
    limit = timeout + Framing(BAUD).wire_time(8 + 7)

    async def ticker() -> None:  # other work on the loop (another bus, the live table)
        while True:
            await asyncio.sleep(0.004)

    async def main() -> None:
        began = time.perf_counter()
        other = asyncio.create_task(ticker())
        async with Bus(PortSettings(bus.port, baudrate=BAUD)) as b:
            for _ in range(5):
                assert (await b.read(3, Table.INPUT, 30008, 1, timeout=0.5)).values
                start = time.perf_counter()
                with pytest.raises(DeviceTimeout):
                    await b.read(9, Table.INPUT, 30008, 1, timeout=timeout)
                dead.append(time.perf_counter() - start)
        other.cancel()
        took.append(time.perf_counter() - began)

    loop = CoarseLoop()
    try:
        loop.run_until_complete(main())
    finally:
        loop.close()
    assert min(dead) >= limit  # never expired early
    # the ticker's 250 turns a second, and a handful a transaction: no spin
    assert loop.turns < 250 * took[0] * 2 + 10 * 20
