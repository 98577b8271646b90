"""The live display, rendered into a StringIO console after real scans of a simulated bus."""

from __future__ import annotations

import asyncio
import dataclasses
import io
from collections.abc import Callable, Collection

from conftest import ANSWERED, dead_at
from rich.console import Console

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.live import PollView

SEEDS = ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
         "banner-ez-array@5"]
def scanned(bus: SimulatedBus, scans: int = 1, dead: Collection[int] = ()) -> Scheduler:
    specs = [(s.split("@")[0], int(s.split("@")[1])) for s in SEEDS]
    site = from_specs(bus.port, specs, baudrate=115200, timeout=ANSWERED, check_serial=False)
    scheduler = Scheduler(dead_at(site, dead))

    async def run() -> None:
        await scheduler.open()
        try:
            for _ in range(scans):
                await scheduler.scan_once(lambda d, r: None)
        finally:
            await scheduler.close()

    asyncio.run(run())
    return scheduler


def show(view: PollView, width: int, height: int) -> list[str]:
    out = io.StringIO()
    Console(file=out, width=width, height=height, color_system=None).print(view)
    return out.getvalue().splitlines()


def test_a_small_terminal_gets_one_line_per_device_and_the_footer_still_shows(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim(*SEEDS, faults=["3:dead"])
    bus.set(2, "air_gap_cm", 321)
    view = PollView(scanned(bus, dead=[3]).buses, title="simulated bus")
    lines = show(view, 80, 24)
    assert len(lines) <= 24 and all(len(line) <= 80 for line in lines)
    assert lines[0].split(" · ")[1:3] == ["4/5 online", "5 scans"]
    radar = next(line for line in lines if line.startswith("radar-level@2"))
    assert "air_gap_cm 321 cm" in radar
    # the dead device: one line saying why, not fifteen dashes
    dead = next(i for i, line in enumerate(lines) if line.startswith("huiwen-aq@3"))
    assert "timeout: no reply from unit 3" in lines[dead]
    assert "(15 fields not read)" in " ".join(lines[dead:dead + 3])
    # the footer: the bus, then each device's health
    footer = lines.index(next(line for line in lines if line.startswith("bus ")))
    assert lines[footer].endswith("transactions/s") and "115200 8N1" in lines[footer]
    # at 80 columns, counters that are 0 everywhere (retried, late, garbled) make room
    assert lines[footer + 1].split()[:5] == ["device", "state", "ok", "timeout", "except"]
    health = {line.split()[0]: line.split()[1:] for line in lines[footer + 2:]}
    # every attempt counted: the Huiwen's read and its retry both timed out
    assert health["huiwen-aq@3"][:4] == ["retrying", "0", "2", "0"]
    assert health["radar-level@2"][:4] == ["online", "5", "0", "0"]


def test_a_tall_terminal_gets_one_row_per_field_with_status_and_age(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim(*SEEDS)
    bus.set(3, "co2_level", "MODERATE")
    lines = show(PollView(scanned(bus, scans=2).buses, title="simulated bus"), 100, 60)
    row = next(line for line in lines if " co2_level " in line)
    cells = [c.strip() for c in row.split("│")]
    assert cells[1:] == ["co2_level", "MODERATE", "", "warning", "ok", cells[-1]]
    assert cells[-1].endswith(" s")  # the age of the reading
    assert lines[0].split(" · ")[2] == "10 scans"


def test_the_trend_column_draws_what_the_readings_did(sim: Callable[..., SimulatedBus]) -> None:

    from rtupoll.model.interpret import field_words, interpret

    bus = sim("huiwen-aq@3", tick=None)
    scheduler = scanned_one(bus)
    wall = [0.0]
    view = PollView(scheduler.buses, title="t", wall=lambda: wall[0])
    dev = scheduler.buses[0].devices[0]
    co2 = dev.config.profile.field("co2")
    first = dev.stats.latest["co2"]
    for i, ppm in enumerate((500, 700, 900)):  # three readings a bin apart
        r = dataclasses.replace(first, time=first.time + 15 * i,
                                value=interpret(co2, field_words(co2, ppm)))
        dev.stats.latest["co2"] = r
        wall[0] = r.time
        lines = show(view, 140, 60)
    head = next(line for line in lines if line.startswith("device"))
    assert head.rstrip().endswith("trend")
    row = next(line for line in lines if " co2 " in line)
    assert row.rstrip().endswith("▁▅█")  # 500, 700, 900 between their low and high
    assert show(view, 80, 60)[1].rstrip().endswith("age")  # no room: no trend column


def test_narrow_no_column_is_dropped(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim(*SEEDS, faults=["3:dead"])
    view = PollView(scanned(bus, dead=[3]).buses, title="simulated bus", live=False)
    out = io.StringIO()
    Console(file=out, width=60, color_system=None).print(view)
    lines = out.getvalue().splitlines()
    assert all(len(line) <= 60 for line in lines)
    head = next(line for line in lines if "┃" in line)
    assert [c.strip() for c in head.split("┃")] == ["field", "value", "unit", "status"]
    assert any(line.startswith("radar-level@2") for line in lines)  # its own row
    co2 = next(line for line in lines if line.startswith("co2 "))  # the dead Huiwen's
    assert "timeout" in co2  # the failed read says so in the one column
    assert next(line for line in lines if line.startswith("temperature ")).split("│")[1:3] \
        and any(line.split("│")[-1].strip() == "ok" for line in lines)
    assert "t/o timeout" in lines[-1]  # the footer's short names, explained


def scanned_one(bus: SimulatedBus) -> Scheduler:
    site = from_specs(bus.port, [("huiwen-aq", 3)], baudrate=115200, timeout=ANSWERED,
                      check_serial=False)
    scheduler = Scheduler(site)

    async def run() -> None:
        await scheduler.open()
        try:
            await scheduler.scan_once(lambda d, r: None)
        finally:
            await scheduler.close()

    asyncio.run(run())
    return scheduler
