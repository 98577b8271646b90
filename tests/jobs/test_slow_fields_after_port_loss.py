"""A field on a slow ``interval`` whose latest reading failed is read again in the first
cycle after the line is back, not when its interval next comes round (in virtual time).

An adapter unplugged for 2 s fails every field of the device being read, the SDM120's
energy totals (``interval: 60``) too, though they were read a moment before; with the
line back, the meter answers at once, and its totals must have values again in that
first cycle (they stayed null for up to a minute: HA showed them unknown, /metrics
dropped the counters).
"""

from __future__ import annotations

import asyncio
from typing import Any

from virtual import VirtualBus, simulated

from rtupoll.config.site import from_specs
from rtupoll.errors import PortError
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.jobs.stats import Reading, Status
from rtupoll.rtu import Table
from rtupoll.rtu.transaction import ReadResult

SLOW = {"import_active_energy", "export_active_energy", "total_active_energy"}


class Unplugged:
    """The virtual bus behind an adapter that can be pulled out: while ``gone``, every
    read fails at once for the port, as the real one does."""

    def __init__(self, bus: VirtualBus) -> None:
        self.bus, self.gone = bus, False

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        if self.gone:
            raise PortError("/dev/ttyUSB0: the port is gone")
        return await self.bus.read(unit, table, address, count, timeout=timeout,
                                   retries=retries, patience=patience, idle_gap=idle_gap)


def test_slow_fields_are_read_in_the_first_cycle_after_the_port_is_back() -> None:
    virtual, clock = simulated(["eastron-sdm120@1"])
    line = Unplugged(virtual)
    config = from_specs("/dev/null", [("eastron-sdm120", 1)], interval=1.0,
                        check_serial=False).buses[0]
    bp = BusPoller(config, line, backoff=Backoff(), clock=clock, wall=clock)  # type: ignore[arg-type]
    dev = bp.devices[0]
    cycles: list[tuple[float, dict[str, Reading]]] = []

    def sink(_: Any, readings: list[Reading]) -> None:
        cycles.append((clock.now, {r.field.name: r for r in readings}))

    async def run_until(end: float) -> None:
        while clock.now < end:
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, sink)

    start = clock.now
    asyncio.run(run_until(start + 10))
    first = cycles[0][1]
    assert first.keys() >= SLOW and all(first[n].ok for n in SLOW)
    assert not SLOW & cycles[1][1].keys()  # in between, not read: their interval is 60 s
    line.gone = True  # unplugged at 10 s, for 2 s
    gone_from = len(cycles)
    asyncio.run(run_until(start + 12))
    lost = [rs for _, rs in cycles[gone_from:]]
    assert lost and all(r.status is Status.PORT for rs in lost for r in rs.values())
    assert lost[0].keys() >= SLOW  # the port took the totals too: null in every output
    line.gone = False
    back_from = len(cycles)
    asyncio.run(run_until(start + 20))
    back = cycles[back_from][1]
    assert all(r.ok for r in back.values())
    assert back.keys() >= SLOW, "the totals wait for their interval: null for ~50 s"
    assert all(back[n].value is not None for n in SLOW)
    # and then their interval again: not in the next cycles
    assert not any(SLOW & rs.keys() for _, rs in cycles[back_from + 1:])

