"""One virtual bus and one virtual clock for every test that runs in virtual time.

The clock is the project's own ``rtupoll.sim.virtual.VirtualClock``: time passes only
when a test or a bus moves it, so a timeout, a backoff or five minutes of polling cost
no wall-clock time and no other process can stretch them.

The bus is the project's own ``VirtualBus`` where the subject is what happens on a line
(the simulator's engine answers, with its faults, under the real line discipline):
``simulated(...)`` builds one over simulated devices. Where the subject is the
scheduler's reaction to an outcome a test picks call by call (a timeout at the third
request, an exception for one block), ``ScriptedBus`` answers on the same clock, each
outcome costing what it would on the line.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError
from rtupoll.jobs.scheduler import BusPoller
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.transaction import Evidence
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build
from rtupoll.sim.virtual import VirtualBus, VirtualClock

__all__ = ["OK_COST", "START", "Behaviour", "ScriptedBus", "VirtualBus", "VirtualClock",
           "poll_for", "simulated"]

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


async def poll_for(bp: BusPoller, clock: VirtualClock, seconds: float) -> None:
    """The bus loop without sleeping: the clock jumps to the next device due."""
    end = clock.now + seconds
    while clock.now < end:
        dev = bp.next_device()
        clock.now = max(clock.now, dev.next_due)
        await bp.run_one(dev, lambda d, rs: None)


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

    def late(self, unit: int) -> int:
        return 0  # late replies seen from ``unit`` (none here)

    adapter_latency = 0.0  # BusLike: no USB adapter

    def evidence(self, unit: int) -> Evidence:
        return Evidence(late=self.late(unit))  # nothing measured

    def set_patience(self, unit: int, seconds: float) -> None:
        pass

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0) -> tuple[int, ...]:
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
        return tuple(range(count))
