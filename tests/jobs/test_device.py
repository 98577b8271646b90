"""Device I/O: fields through the planner and the bus, variants, the profile's timing.

Against the simulator for the five seed profiles (the decoded values must equal what
the simulated device holds, in as many requests as the plan has blocks), and against
a recording fake for what is sent where.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import pytest

from rtupoll.config.library import load_one
from rtupoll.errors import DeviceException, DeviceTimeout
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.jobs.device import probe_variant, read_block, read_fields, timing
from rtupoll.model.planner import plan
from rtupoll.model.profile import Profile
from rtupoll.rtu import Table
from rtupoll.rtu.transaction import Evidence, ReadResult
from rtupoll.sim.runner import SimulatedBus

T = TypeVar("T")
Sim = Callable[..., SimulatedBus]
SEEDS = {"net-irnet-pro": 1, "radar-level": 2, "huiwen-aq": 3, "co2meter-an117": 5,
         "banner-ez-array": 7}


def run(coro: Coroutine[Any, Any, T]) -> T:
    return asyncio.run(coro)


class Recorder:
    """A bus that answers every read with the register addresses and records the calls."""

    def __init__(self, fail: dict[int, Exception] | None = None) -> None:
        self.calls: list[tuple[int, Table, int, int, float, int]] = []
        self.fail = fail or {}

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        self.calls.append((unit, table, address, count, timeout, retries))
        if address in self.fail:
            raise self.fail[address]
        return ReadResult(tuple((address + i) & 0xFFFF for i in range(count)), Evidence())


@pytest.mark.parametrize("pid", sorted(SEEDS))
def test_default_fields_of_each_seed_device(sim: Sim, pid: str) -> None:
    unit = SEEDS[pid]
    profile = load_one(pid)
    bus_sim = sim(f"{pid}@{unit}", tick=None)
    settings = PortSettings(bus_sim.port, baudrate=profile.serial.baudrate,
                            deassert_dtr=profile.serial.deassert_dtr)

    async def go() -> tuple[list[Any], int]:
        async with Bus(settings) as bus:
            got = await read_fields(bus, profile, unit, profile.default_fields())
            return list(got.values), bus.stats.transactions
    got, transactions = run(go())
    assert [fv.field.name for fv in got] == [f.name for f in profile.default_fields()]
    for fv in got:
        assert fv.value == bus_sim.get(unit, fv.field.name).value, fv.field.name
    assert transactions == len(plan(profile.default_fields(), profile))


def test_irnet_variant_probe(sim: Sim) -> None:
    p = load_one("net-irnet-pro")
    bus_sim = sim("net-irnet-pro@1", "net-irnet-pro@2", options=["net-irnet-pro@2.variant=0"],
                  tick=None)

    async def go() -> tuple[int | None, int | None, list[str]]:
        async with Bus(PortSettings(bus_sim.port, baudrate=4800)) as bus:
            new, old = (await probe_variant(bus, p, 1)).number, \
                (await probe_variant(bus, p, 2)).number
            wanted = [p.field("full_scale"), p.field("calibration_gas_level")]
            got = await read_fields(bus, p, 2, wanted, variant=old)
            assert got.missing == {"calibration_gas_level": "not present (data structure 0)"}
            probed = await read_fields(bus, p, 2, wanted, probe=True)
            assert (probed.variant, probed.missing) == (0, got.missing)
            blind = await read_fields(bus, p, 2, wanted)  # asked blindly: the device says no
            assert [(f.name, e.code) for f, e in blind.refused] == [("calibration_gas_level", 2)]
            assert isinstance(blind.error(), DeviceException)
            assert [fv.field.name for fv in blind.values] == ["full_scale"]  # bisected
            return new, old, [fv.field.name for fv in got.values]
    assert run(go()) == (1, 0, ["full_scale"])


def test_probe_variant_without_a_variant_and_other_errors() -> None:
    none = run(probe_variant(Recorder(), load_one("huiwen-aq"), 3))
    assert (none.number, none.evidence) == (None, None)  # nothing asked
    p = load_one("net-irnet-pro")
    with pytest.raises(DeviceException):  # exception 04 is not listed in on_exception
        run(probe_variant(Recorder({0x400: DeviceException(4, unit=1)}), p, 1))
    refused = DeviceException(2, unit=1)
    refused.evidence = Evidence(0.004, attempts=1)  # an exception reply's reply time
    zero = run(probe_variant(Recorder({0x400: refused}), p, 1))
    assert (zero.number, zero.evidence) == (0, refused.evidence)  # an answer: its evidence
    value = run(probe_variant(Recorder(), p, 1))
    assert value.number == 0x400 and value.evidence == Evidence()  # the register's value


def test_timing_defaults_come_from_the_profile() -> None:
    co2 = load_one("co2meter-an117")
    rec = Recorder()
    run(read_fields(rec, co2, 0xFE, co2.default_fields()))
    assert rec.calls == [(0xFE, Table.INPUT, 1, 1, 0.15, 2)]
    run(read_fields(rec, co2, 0xFE, co2.default_fields(), timeout=1.0, retries=0))
    assert rec.calls[-1][4:] == (1.0, 0)
    assert timing(co2) == timing(co2, None, None)
    assert timing(co2, 0.3).retries == co2.limits.retries


def test_values_come_back_in_request_order_and_errors_propagate() -> None:
    p: Profile = load_one("huiwen-aq")
    wanted = [p.field(n) for n in ("co2_level", "pm25", "hcho", "pm25")]
    rec = Recorder()
    got = run(read_fields(rec, p, 3, wanted)).values
    assert [fv.field.name for fv in got] == ["co2_level", "pm25", "hcho"]
    assert len(rec.calls) == 2
    assert got[1].raw == (30006,)
    failing = Recorder({30039: DeviceTimeout("no reply")})
    with pytest.raises(DeviceTimeout):
        run(read_fields(failing, p, 3, wanted))
    block = plan(wanted, p)[0]
    got_block = run(read_block(rec, 3, block, timeout=0.1, retries=0))
    assert [fv.field.name for fv in got_block.values] == ["pm25", "hcho"]
    assert got_block.evidence == Evidence()  # what the bus told of the transaction
