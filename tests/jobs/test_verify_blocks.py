"""``poll --verify-blocks``: a device that answers a block read shifted is caught.

The simulator's ``shift=R`` quirk is an undocumented register the device silently
skips: a block read over it returns the registers after it moved down by one, with
no exception (pysolarfocus#61). Rules in virtual time on ``sim.virtual.VirtualBus``;
the command end to end on the simulator's pty.
"""

from __future__ import annotations

import asyncio
import json

from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.config.site import from_specs
from rtupoll.jobs.hole_services import verify_device
from rtupoll.jobs.holes import Mismatch, verify_block
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.model.planner import Block, plan
from rtupoll.rtu import Framing, Table
from rtupoll.sim.device import SimDeviceConfig as SimConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.virtual import VirtualBus, VirtualClock

SHIFT = 30011  # inside the 30010..30011 gap the Huiwen profile lets the planner bridge


def bus(faults: tuple[str, ...] = (), tick: float | None = None) -> tuple[VirtualBus, Engine]:
    clock = VirtualClock()
    engine = Engine([SimConfig(load_one("huiwen-aq"), 3,
                               faults=tuple(parse_fault(f) for f in faults))], tick=tick)
    return VirtualBus(engine, Framing(9600), clock=clock, sleep=clock.sleep), engine


def block() -> Block:
    p = load_one("huiwen-aq")
    return next(b for b in plan(p.default_fields(), p) if b.address == 30006)


def test_a_silent_shift_is_named_with_its_fields_and_addresses() -> None:
    vbus, engine = bus((f"3:shift={SHIFT}",))
    found = asyncio.run(verify_block(vbus, 3, block(), timeout=0.5, retries=0))
    assert isinstance(found, Mismatch)
    assert [f.name for f, _, _ in found.fields] == ["temperature", "humidity"]
    dev = engine.devices[0]
    temperature = dev.field("temperature")
    (_, inblock, alone), = [x for x in found.fields if x[0].name == "temperature"]
    assert alone == dev.words(Table.INPUT, temperature.address, 1)  # alone: the truth
    assert inblock == dev.words(Table.INPUT, temperature.address + 1, 1)  # block: shifted
    text = str(found)
    assert text.startswith("input 0x7536+8: temperature (0x753C) reads")
    assert found.holes() == {(Table.INPUT, 30010), (Table.INPUT, 30011)}


def test_an_honest_device_with_moving_values_is_no_mismatch() -> None:
    vbus, _ = bus(tick=0.002)  # values step every 2 ms: they move between the reads
    assert asyncio.run(verify_block(vbus, 3, block(), timeout=0.5, retries=0)) is None


def test_a_mismatch_stops_bridging_there_and_the_new_plan_verifies() -> None:
    vbus, _ = bus((f"3:shift={SHIFT}",))
    config = from_specs("virtual", [("huiwen-aq", 3)], baudrate=9600).buses[0]
    clock = VirtualClock()
    bp = BusPoller(config, vbus, backoff=Backoff(), clock=clock, wall=clock)
    dev = bp.devices[0]
    said: list[str] = []
    verdicts: list[bool] = []
    asyncio.run(verify_device(dev, vbus, verdicts.append, said.append))
    assert verdicts.count(True) == 1 and len(said) == 1
    assert "silent shift" in said[0] and "0x753C" in said[0] and "no longer bridged" in said[0]
    assert not any(b.address <= SHIFT < b.end for b in dev.blocks if b.table is Table.INPUT)
    verdicts.clear()
    asyncio.run(verify_device(dev, vbus, verdicts.append, said.append))
    assert verdicts and True not in verdicts  # the new plan reads what the fields read alone
    assert len(said) == 1  # and says nothing more


def test_poll_verify_blocks_end_to_end() -> None:
    result = rtupoll("poll", "--simulate", "--fault", f"3:shift={SHIFT}",
                     "huiwen-aq@3", "--verify-blocks", "--once",
                     "--format", "json", "--fields",
                     "pm25,co2,temperature,humidity")
    assert result.returncode == 0, result.stderr
    err = result.stderr
    assert "silent shift" in err and "temperature (0x753C)" in err
    assert "1 disagreed" in err
    records = {r["field"]: r for r in map(json.loads, result.stdout.splitlines())}
    assert {r["status"] for r in records.values()} == {"ok"}
    # read after the re-plan: humidity is its own register, not the padding
    assert records["humidity"]["value"] != 0
