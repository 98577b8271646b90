"""The scheduler's buses run as one task group (structured concurrency), in virtual
time: an error in one bus ends every bus and comes out as itself (``poll`` reports it
as it would from one bus), ``stop`` ends them all with no task left behind, and a bus
a reload adds joins the group while one it removes leaves it."""

from __future__ import annotations

import asyncio
import dataclasses

import pytest
from virtual import START, ScriptedBus, VirtualClock

from rtupoll.config.site import BusConfig, Site, from_specs
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading


def bus(name: str, address: int) -> BusConfig:
    one = from_specs("/dev/null", [("huiwen-aq", address)], interval=0.0).buses[0]
    return dataclasses.replace(one, name=name, port=f"/dev/{name}")


def scheduler(*buses: BusConfig) -> tuple[Scheduler, dict[str, ScriptedBus]]:
    clock = VirtualClock(START)
    lines: dict[str, ScriptedBus] = {}

    def open_bus(config: BusConfig) -> ScriptedBus:
        lines[config.name] = ScriptedBus(clock)
        return lines[config.name]

    return Scheduler(Site(buses), open_bus=open_bus, clock=clock), lines  # type: ignore[arg-type]


def test_an_error_in_one_bus_ends_every_bus_and_comes_out_as_itself() -> None:
    sched, lines = scheduler(bus("a", 1), bus("b", 2))
    cycles = {"a": 0, "b": 0}

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        name = "a" if dev.config.address == 1 else "b"
        cycles[name] += 1
        if name == "b" and cycles["b"] == 3:
            raise BrokenPipeError("the reader went away")

    async def main() -> None:
        await sched.open()
        with pytest.raises(BrokenPipeError, match="the reader went away"):
            await sched.run(sink, asyncio.Event())
        assert sched._tasks == {}
        await sched.close()

    asyncio.run(main())
    assert cycles["b"] == 3 and cycles["a"] >= 1
    a_calls = len(lines["a"].calls)
    assert a_calls > 0  # bus a ran beside b, and stopped with it (no task left running)


def test_stop_ends_every_bus_and_a_reload_adds_and_removes_buses_in_the_group() -> None:
    sched, lines = scheduler(bus("a", 1), bus("b", 2))
    seen: list[str] = []
    stop = asyncio.Event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        seen.append(dev.config.name)

    async def main() -> None:
        await sched.open()
        run = asyncio.create_task(sched.run(sink, stop))
        while not {"huiwen-aq@1", "huiwen-aq@2"} <= set(seen):
            await asyncio.sleep(0)
        changes = await sched.reload(Site((bus("a", 1), bus("c", 3))))
        assert "closed bus b (/dev/b)" in changes
        assert set(sched._tasks) == set(sched.buses)  # c joined, b left
        seen.clear()
        while "huiwen-aq@3" not in seen:
            await asyncio.sleep(0)
        b_calls = len(lines["b"].calls)
        for _ in range(20):
            await asyncio.sleep(0)
        assert len(lines["b"].calls) == b_calls  # b polls no more
        stop.set()
        await run  # returns: every bus ended, nothing raised
        assert sched._tasks == {}
        await sched.close()

    asyncio.run(main())
