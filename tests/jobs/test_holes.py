"""Holes in a register map (rtupoll.jobs.holes): found by bisection, never bridged again.

The device under test is the simulator's Huiwen module with an undocumented hole at
input 30011, inside the 30010..30011 gap its profile lets the planner bridge; polling
runs on ``sim.virtual.VirtualBus`` in virtual time.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.config.site import from_specs
from rtupoll.errors import ConfigError, DeviceException, FaultSpecError
from rtupoll.jobs.hole_services import RememberHoles
from rtupoll.jobs.holes import Bisection, HoleStore, bisect, gaps, pieces, show
from rtupoll.jobs.scheduler import Backoff, BusPoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.model.planner import Block, plan
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.messages import ReadRequest
from rtupoll.rtu.transaction import ReadResult
from rtupoll.sim.device import SimDevice
from rtupoll.sim.device import SimDeviceConfig as SimConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.virtual import VirtualBus, VirtualClock

HOLE = 30011  # wire address (the Huiwen module addresses registers directly)


def huiwen_block() -> Block:
    p = load_one("huiwen-aq")
    return next(b for b in plan(p.default_fields(), p) if b.address == 30006)


def test_gaps_and_pieces_of_a_block() -> None:
    block = huiwen_block()
    assert (block.address, block.count) == (30006, 8)
    assert gaps(block) == [range(30010, 30012)]
    cut = pieces(block)
    assert [(b.address, b.count) for b in cut] == [(30006, 4), (30012, 2)]
    assert [f.name for b in cut for f in b.fields] == [f.name for f in block.fields]
    assert show({(Table.INPUT, 5), (Table.INPUT, 6), (Table.INPUT, 9)}) == \
        "input 0x0005-0x0006, 0x0009"


def test_the_planner_never_bridges_a_hole_but_still_reads_fields_there() -> None:
    p = load_one("huiwen-aq")
    holes = {(Table.INPUT, HOLE)}
    blocks = plan(p.default_fields(), p, holes=holes)
    assert not any(b.table is Table.INPUT and b.address <= HOLE < b.end for b in blocks)
    assert {f.name for b in blocks for f in b.fields} == {f.name for f in p.default_fields()}
    # a field whose own register is a hole (the device refused it) is still read, alone
    alone = plan(p.default_fields(), p, holes={(Table.INPUT, 30006)})
    assert {f.name for b in alone for f in b.fields} == {f.name for f in p.default_fields()}
    [pm25] = [b for b in alone if b.table is Table.INPUT and b.address <= 30006 < b.end]
    assert (pm25.address, pm25.count, [f.name for f in pm25.fields]) == (30006, 1, ["pm25"])


def test_the_simulated_hole_refuses_any_read_over_it() -> None:
    p = load_one("huiwen-aq")
    plain = SimDevice(SimConfig(p, 3), tick=None)
    holed = SimDevice(SimConfig(p, 3, faults=(parse_fault(f"3:hole={HOLE}"),)), tick=None)

    block = ReadRequest(3, 4, 30006, 8)
    assert plain.handle(block) is not None and plain.handle(block)[1] == 4  # type: ignore[index]
    assert holed.handle(block) == bytes.fromhex("03 84 02") + holed.handle(block)[3:]  # type: ignore[index]
    alone = holed.handle(ReadRequest(3, 4, 30012, 1))
    assert alone is not None and alone[1] == 4  # outside the hole: answered
    with pytest.raises(FaultSpecError, match="ADDRESS:hole=REGISTER"):
        parse_fault("hole=5")  # a hole belongs to one device


class Reads(VirtualBus):
    """The virtual bus, counting reads and exception replies."""

    exceptions: int = 0

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        try:
            return await super().read(unit, table, address, count, timeout=timeout,
                                      retries=retries, patience=patience, idle_gap=idle_gap)
        except DeviceException:
            self.exceptions += 1
            raise


def holed_bus(fault: str = f"3:hole={HOLE}") -> tuple[VirtualClock, BusPoller, Reads]:
    clock = VirtualClock()
    engine = Engine([SimConfig(load_one("huiwen-aq"), 3, faults=(parse_fault(fault),))],
                    tick=None)
    bus = Reads(engine, Framing(9600), clock=clock, sleep=clock.sleep)
    config = from_specs("virtual", [("huiwen-aq", 3)], baudrate=9600).buses[0]
    return clock, BusPoller(config, bus, backoff=Backoff(), clock=clock, wall=clock,
                            rand=lambda: 0.5), bus


def test_one_bisection_then_every_cycle_reads_everything_without_exception_02() -> None:
    clock, bp, bus = holed_bus()
    dev = bp.devices[0]

    async def cycles(n: int) -> list[list[str]]:
        out = []
        for _ in range(n):
            clock.now = max(clock.now, dev.next_due)
            got: list[list[str]] = []

            def sink(d: object, rs: list[Reading], got: list[list[str]] = got) -> None:
                got.append([r.status for r in rs])

            await bp.run_one(dev, sink)
            out += got
        return out

    first = asyncio.run(cycles(1))
    assert first == [["ok"] * len(dev.config.fields)]  # read in full in that very cycle
    assert dev.stats.exceptions[2] == 1  # the block read that found it
    assert dev.holes.registers == {(Table.INPUT, HOLE)}
    assert dev.stats.holes and "0x753B" in dev.stats.holes[0] and "exception 02" in \
        dev.stats.holes[0]
    assert not any(b.address <= HOLE < b.end for b in dev.blocks if b.table is Table.INPUT)
    seen = bus.exceptions
    later = asyncio.run(cycles(50))
    assert len(later) == 50 and all(s == ["ok"] * len(dev.config.fields) for s in later)
    assert bus.exceptions == seen  # never exception 02 again
    assert dev.stats.exceptions[2] == 1


def test_a_refused_field_of_its_own_is_found_and_every_other_field_read() -> None:
    _, _, bus = holed_bus("3:hole=30006")  # pm25's own register
    block = huiwen_block()

    async def go() -> Bisection | None:
        return await bisect(bus, 3, block, timeout=0.5, retries=0)

    found = asyncio.run(go())
    assert found is not None
    assert [(f.name, e.code) for f, e in found.refused] == [("pm25", 2)]
    assert {v.field.name for v in found.values} == {f.name for f in block.fields} - {"pm25"}
    assert found.holes == {(Table.INPUT, 30006)}  # the gap read: only the field is a hole
    # the piece 30006+4 refused; its halves 30006+2 (refused: 30006 refused, 30007
    # reads) and 30008+2; the other piece 30012+2; the gap 30010+2
    assert bus.exceptions == 3 and len(bus.sent) == 7


def test_the_state_file_keeps_holes_per_device_profile_and_variant(tmp_path: Path) -> None:
    site = tmp_path / "site.yaml"
    store = HoleStore.for_site(site)
    assert store.path == tmp_path / "site.holes.json"
    store.put("air", "huiwen-aq", None, {(Table.INPUT, HOLE)})
    again = HoleStore(store.path)
    assert again.get("air", "huiwen-aq", None) == {(Table.INPUT, HOLE)}
    assert again.get("air", "net-irnet-pro", None) == set()  # another profile: afresh
    assert again.get("air", "huiwen-aq", 1) == set()  # another variant: afresh
    assert json.loads(store.path.read_text())["devices"]["air"]["holes"] == [["input", HOLE]]
    store.path.write_text("not json")
    with pytest.raises(ConfigError, match="delete it"):
        HoleStore(store.path)


def test_remembered_holes_are_planned_around_from_the_start(tmp_path: Path) -> None:
    store = HoleStore(tmp_path / "site.holes.json")
    site = from_specs("virtual", [("huiwen-aq", 3)], baudrate=9600)
    name = site.buses[0].devices[0].name
    store.put(name, "huiwen-aq", None, {(Table.INPUT, HOLE)})
    said: list[str] = []
    engine = Engine([SimConfig(load_one("huiwen-aq"), 3)], tick=None)
    scheduler = Scheduler(site, open_bus=lambda b: VirtualBus(engine, Framing(9600)))
    asyncio.run(RememberHoles(HoleStore(store.path), said.append).start(scheduler))
    dev = scheduler.pollers()[0]
    assert dev.holes.registers == {(Table.INPUT, HOLE)}
    assert not any(b.address <= HOLE < b.end for b in dev.blocks if b.table is Table.INPUT)
    assert said and "learned earlier" in said[0]


def test_poll_remember_holes_end_to_end(tmp_path: Path,
                                        sim: Callable[..., SimulatedBus]) -> None:
    line = sim("huiwen-aq@3", faults=[f"3:hole={HOLE}"])
    site = tmp_path / "site.yaml"
    site.write_text(f"buses:\n  - port: {line.port}\n    baudrate: 9600\n    devices:\n"
                    "      - {name: air, profile: huiwen-aq, address: 3}\n")
    args = ["poll", "-c", str(site), "--remember-holes", "--once", "--format", "json"]
    first = rtupoll(*args)
    assert first.returncode == 0, first.stderr
    assert {json.loads(x)["status"] for x in first.stdout.splitlines()} == {"ok"}
    kept = json.loads((tmp_path / "site.holes.json").read_text())["devices"]["air"]
    assert kept == {"profile": "huiwen-aq", "variant": None, "holes": [["input", HOLE]]}
    refused = line.engine.requests
    second = rtupoll(*args)
    assert second.returncode == 0, second.stderr
    assert "learned earlier" in second.stderr
    assert {json.loads(x)["status"] for x in second.stdout.splitlines()} == {"ok"}
    # the second run planned around the hole from the start: no bisection, no 02
    assert refused == 3 + 2 + 3  # blocks, the fields alone, the gap halved: 2, 1, 1
    assert line.engine.requests - refused == 4  # its four blocks now, nothing more
    assert rtupoll("poll", "-p", line.port, "huiwen-aq@3",
                   "--remember-holes", "--once").returncode == 2


def test_a_block_whose_own_field_is_refused_is_split_once_then_the_field_read_alone(
        ) -> None:
    clock, bp, bus = holed_bus("3:hole=30006")  # pm25's own register
    dev = bp.devices[0]
    statuses: list[dict[str, str]] = []

    async def cycles(n: int) -> None:
        for _ in range(n):
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: statuses.append(
                {r.field.name: r.status for r in rs}))

    asyncio.run(cycles(1))
    after_first = len(bus.sent)
    asyncio.run(cycles(5))
    assert dev.holes.registers == {(Table.INPUT, 30006)}
    for got in statuses:  # every cycle: every other field ok, pm25 with its exception
        assert got.pop("pm25") == "exception"
        assert set(got.values()) == {"ok"}
    assert dev.stats.exceptions[2] == 6  # the refused field reported every scan
    assert len(bus.sent) - after_first == 5 * len(dev.blocks)  # no splitting again
    assert any(b.fields[0].name == "pm25" and len(b.fields) == 1 for b in dev.blocks)
