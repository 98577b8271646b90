"""A late reply is never decoded as the answer to another request (issue: wrong values
marked ok). Replies come late by 1, 2, 3 and 10 timeouts, and at random, from a device
read one field at a time (every reply has the same shape) and from a block-read
device, with no retries and with the profile's; every value is pinned, so a reply
given to the wrong request would show as another field's value.

Every case runs in virtual time (tests/virtual.py: the scheduler, the line's rules and
the simulator's engine, with late replies exactly as late as asked, whatever the
machine's load); one runs the real path too: the scheduler, the pymodbus bus on a pty,
the simulator.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import pytest
from virtual import simulated

from rtupoll.config.site import Site, from_specs
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.sim.runner import SimulatedBus

TIMEOUT = 0.1
RADAR = {"air_gap_cm": 111, "air_gap_mm": 2222, "level_cm": 333, "level_mm": 4444,
         "range_cm": 555, "blind_zone_cm": 66}
HUIWEN = {"co2": 1001, "pm25": 102, "temperature": 23, "humidity": 44, "tvoc": 0.5}
DEVICES = {"radar-level@2": RADAR, "huiwen-aq@3": HUIWEN}
SCANS = {"radar-level@2": 5, "huiwen-aq@3": 25}  # six reads a scan / one block a scan


def late(k: float, n: int) -> str:
    """A fault: request ``n`` on the bus is answered ``k`` timeouts after its deadline."""
    return f"slow={(1 + k) * TIMEOUT:g}@{n}"


def poll(sim: Callable[..., SimulatedBus] | None, device: str, faults: list[str],
         retries: int | None, scans: int) -> tuple[list[Reading], DevicePoller]:
    """``scans`` scans of ``device`` with ``faults``: on a pty against the simulator
    (``sim``), or in virtual time (``sim`` None)."""
    unit = int(device.split("@")[1])
    profile, _, address = device.partition("@")

    def site(port: str) -> Site:
        return from_specs(port, [(profile, int(address))], baudrate=9600,
                          fields=list(DEVICES[device]), timeout=TIMEOUT, retries=retries,
                          check_serial=False)
    if sim is None:
        virtual, clock = simulated([device], faults, seed=3, turnaround=0.002, baudrate=9600)
        for name, value in DEVICES[device].items():
            virtual.engine.device(unit).pin(name, value)
        scheduler = Scheduler(site("virtual"), open_bus=lambda _: virtual, clock=clock)
    else:
        bus = sim(device, faults=faults, seed=3, turnaround=0.002, tick=None)
        for name, value in DEVICES[device].items():
            bus.set(unit, name, value)
        scheduler = Scheduler(site(bus.port))
    readings: list[Reading] = []

    async def go() -> None:
        await scheduler.open()
        try:
            for _ in range(scans):
                await scheduler.scan_once(lambda dev, rs: readings.extend(rs))
        finally:
            await scheduler.close()

    asyncio.run(go())
    return readings, scheduler.pollers()[0]


def check(readings: list[Reading], device: str) -> int:
    """Every value read is the pinned one; returns how many were read."""
    wrong = [(r.field.name, r.value.value) for r in readings if r.value is not None
             and r.value.value != pytest.approx(DEVICES[device][r.field.name])]
    assert wrong == []
    return sum(r.value is not None for r in readings)


LATE_BY_1_2_3_AND_10 = [late(1, 3), late(2, 9), late(3, 15), late(10, 21)]


@pytest.mark.parametrize("retries", [0, None], ids=["retries-0", "profile-retries"])
@pytest.mark.parametrize("device", list(DEVICES))
def test_replies_late_by_1_2_3_and_10_timeouts(device: str, retries: int | None) -> None:
    readings, poller = poll(None, device, LATE_BY_1_2_3_AND_10, retries,
                            scans=SCANS[device])
    ok = check(readings, device)
    assert ok >= len(readings) // 2  # it kept reading, not just refusing
    assert poller.stats.late >= 3  # the late replies were heard and counted as such


def test_on_the_wire_replies_late_by_1_2_3_and_10_timeouts(
        sim: Callable[..., SimulatedBus]) -> None:
    """The real path, for the device whose replies all have the same shape."""
    readings, poller = poll(sim, "radar-level@2", LATE_BY_1_2_3_AND_10, 0,
                            scans=SCANS["radar-level@2"])
    ok = check(readings, "radar-level@2")
    assert ok >= len(readings) // 2
    assert poller.stats.late >= 3


@pytest.mark.parametrize("device", list(DEVICES))
def test_replies_late_at_random(device: str) -> None:
    readings, poller = poll(None, device, [f"slow={2.5 * TIMEOUT:g}@25%"], 0,
                            scans=2 * SCANS[device])
    ok = check(readings, device)
    assert ok > 0
    assert poller.stats.late > 0
