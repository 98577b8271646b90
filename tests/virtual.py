"""One virtual bus and one virtual clock for every test that runs in virtual time.

The clock is the project's own ``rtupoll.sim.virtual.VirtualClock``: time passes only
when a test or a bus moves it, so a timeout, a backoff or five minutes of polling cost
no wall-clock time and no other process can stretch them. ``run_virtual`` runs a
coroutine on an event loop whose time is that clock and which, when every task waits
(a sleep, a timeout), jumps the clock to the next timer instead of waiting for it: the
project's own loops (``BusPoller.run``: its idle waits, its timeouts) run as they are.

The bus is the project's own ``VirtualBus`` where the subject is what happens on a line
(the simulator's engine answers, with its faults, under the real line discipline):
``simulated(...)`` builds one over simulated devices. Where the subject is the
scheduler's reaction to an outcome a test picks call by call (a timeout at the third
request, an exception for one block), ``ScriptedBus`` answers on the same clock, each
outcome costing what it would on the line.
"""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError
from rtupoll.jobs.scheduler import BusPoller, Sink
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import Line, UnitCounts
from rtupoll.rtu.transaction import Evidence, ReadResult
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build
from rtupoll.sim.virtual import VirtualBus, VirtualClock

__all__ = ["OK_COST", "START", "Behaviour", "ScriptedBus", "VirtualBus", "VirtualClock",
           "heard_nothing", "polled", "run_virtual", "simulated"]

T = TypeVar("T")
HANG = 10.0  # real seconds the virtual loop waits for another thread when no timer is set

START = 1000.0  # virtual clocks start here: a wall clock is never near zero either


def simulated(devices: Sequence[str], faults: Sequence[str] = (), *, seed: int = 1,
              turnaround: float = 0.002, baudrate: int = 115200
              ) -> tuple[VirtualBus, VirtualClock]:
    """A ``VirtualBus`` over the simulator's engine serving ``devices`` ("huiwen-aq@3")
    with ``faults`` ("3:crc@2-5"), and the virtual clock it runs on."""
    config = build(list(devices), faults=tuple(faults), seed=seed, turnaround=turnaround,
                   tick=None)
    clock = VirtualClock(START)
    engine = Engine(config.devices, config.faults, seed=seed, tick=None)
    return VirtualBus(engine, Framing(baudrate), clock=clock, sleep=clock.sleep), clock


class _Jumping(selectors.DefaultSelector):
    """The loop's selector: what is ready now (the loop's own wake-ups); when nothing is,
    the wait for the next timer passes at once, on the clock."""

    def __init__(self, clock: VirtualClock) -> None:
        super().__init__()
        self.clock = clock

    def select(self, timeout: float | None = None) -> list[Any]:
        ready: list[Any] = super().select(0)
        if ready or timeout == 0:
            return ready
        if timeout is None:  # no timer: only another thread can wake the loop (an executor)
            ready = super().select(HANG)
            if not ready:
                raise RuntimeError("every task waits and no timer is set: a hang in "
                                   "virtual time")
            return ready
        self.clock.now += timeout
        return []


class _VirtualLoop(asyncio.SelectorEventLoop):
    def __init__(self, clock: VirtualClock) -> None:
        super().__init__(_Jumping(clock))
        self.clock = clock

    def time(self) -> float:
        return self.clock.now


def run_virtual(main: Coroutine[Any, Any, T], clock: VirtualClock) -> T:
    """``asyncio.run(main)`` on ``clock``'s time (module docstring)."""
    with asyncio.Runner(loop_factory=lambda: _VirtualLoop(clock)) as runner:
        return runner.run(main)


async def polled(bp: BusPoller, seconds: float, sink: Sink | None = None) -> None:
    """``bp.run`` itself, stopped after ``seconds`` of the loop's time (virtual time under
    ``run_virtual``); ``sink`` gets each cycle's readings."""
    stop = asyncio.Event()
    asyncio.get_running_loop().call_later(seconds, stop.set)
    await bp.run(sink or (lambda d, rs: None), stop)


_QUIET = Line(Framing(9600))  # a line that has heard nothing


def heard_nothing(unit: int) -> UnitCounts:
    """``BusLike.unit_counts`` of a bus that counts nothing (a scripted one)."""
    return UnitCounts(_QUIET, unit)


# (block address, call number) -> ok | slow (answers, but takes 0.8 s) | timeout | crc |
# exc02 (an exception reply with code 02)
Behaviour = Callable[[int, int], str]
OK_COST = 0.02  # virtual seconds an answered read takes


@dataclass
class ScriptedBus:
    """Answers by a behaviour per unit (every unit without one answers ``ok``: the values
    0, 1, 2, ...); records (unit, address, retries) of every call; advances ``clock`` by
    what each outcome costs (a timeout: every attempt's timeout)."""

    clock: VirtualClock
    behaviour: dict[int, Behaviour] = field(default_factory=dict)
    calls: list[tuple[int, int, int]] = field(default_factory=list)

    async def open(self) -> None: ...
    async def close(self) -> None: ...

    adapter_latency = 0.0  # BusLike: no USB adapter
    echo_found = False  # BusLike: no line to hear an echo
    stats = None  # BusLike: counts nothing

    def unit_counts(self, unit: int) -> UnitCounts:
        return heard_nothing(unit)  # no late replies, nothing counted

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        self.calls.append((unit, address, retries))
        what = self.behaviour.get(unit, lambda a, n: "ok")(address, len(self.calls))
        if what == "timeout":
            await self.clock.sleep(timeout * (1 + retries))
            raise DeviceTimeout(f"no response from device {unit}")
        await self.clock.sleep(OK_COST if what != "slow" else 0.8)
        if what == "crc":
            raise FrameError("CRC error")
        if what.startswith("exc"):
            raise DeviceException(int(what[3:]), unit=unit, function=table.read_function)
        return ReadResult(tuple(range(count)), Evidence())  # nothing measured
