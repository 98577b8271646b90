"""``scale_by`` in the scheduler, in virtual time: the ratios are read in every cycle that
reads the fields they scale, so a ratio changed on the meter's keypad is followed at the
next cycle, and a ratio read that fails costs its fields that cycle only."""

from __future__ import annotations

import asyncio

from virtual import simulated

from rtupoll.config.site import from_specs
from rtupoll.errors import FrameError
from rtupoll.jobs.device import read_fields
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.jobs.stats import Reading

DEV = "chint-dtsu666"


def cycles(n: int, faults: tuple[str, ...] = (), fields: tuple[str, ...] = (),
           change: dict[int, int] | None = None) -> list[dict[str, Reading]]:
    """``n`` cycles of a DTSU666 at IrAt 200 holding 0.035 A; before cycle ``k`` of
    ``change``, the meter's IrAt is set to ``change[k]``. Each cycle's readings by field."""
    bus, clock = simulated([f"{DEV}@1"], faults)
    meter = bus.engine.device(1)
    for name, v in {"current_ratio": 200, "voltage_ratio": 1.0, "current_l1": 0.035,
                    "import_active_energy": 45.91}.items():
        meter.pin(name, v)
    site = from_specs("virtual", [(DEV, 1)], interval=1.0, fields=fields, check_serial=False)
    bp = BusPoller(site.buses[0], bus, backoff=Backoff(base=1.0), clock=clock, wall=clock)
    out: list[dict[str, Reading]] = []

    async def go() -> None:
        for k in range(n):
            if change and k in change:
                meter.pin("current_ratio", change[k])
            dev = bp.devices[0]
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: out.append({r.field.name: r for r in rs}))

    asyncio.run(go())
    return out


def amps(c: dict[str, Reading]) -> object:
    r = c["current_l1"]
    return r.value.value if r.value is not None else r.status.value


def test_a_ratio_changed_on_the_meter_is_followed_at_the_next_cycle() -> None:
    got = cycles(3, change={2: 100})
    assert [amps(c) for c in got] == [7.0, 7.0, 3.5]


def test_a_failed_ratio_read_costs_its_fields_that_cycle_only() -> None:
    # request 1 reads the ratios (lowest address); the cycle's other blocks answer
    got = cycles(3, faults=("1:exception=4@1",))
    assert [amps(c) for c in got] == ["unscaled", 7.0, 7.0]
    assert got[0]["frequency"].ok and got[0]["current_l1"].value is None


def test_energies_read_once_a_minute_are_scaled_by_the_ratio_of_their_cycle() -> None:
    got = cycles(3, fields=("import_active_energy",))
    energy = [c["import_active_energy"] for c in got if "import_active_energy" in c]
    assert energy and all(r.value is not None and r.value.value == 9182.0 for r in energy)
    assert all(set(c) <= {"import_active_energy"} for c in got)  # the ratios not reported


def test_read_fields_for_mqtt_get_scales_and_refuses_a_zero_ratio() -> None:
    bus, _ = simulated([f"{DEV}@1"])
    meter = bus.engine.device(1)
    meter.pin("current_ratio", 200)
    meter.pin("current_l1", 0.035)
    p = meter.config.profile
    (fv,) = asyncio.run(read_fields(bus, p, 1, [p.field("current_l1")])).values
    assert fv.value == 7.0
    meter.pin("current_ratio", 0)
    got = asyncio.run(read_fields(bus, p, 1, [p.field("current_l1")]))
    assert got.values == ()
    error = got.error()
    assert isinstance(error, FrameError) and str(error) == (
        "unit 1: current_l1 not scaled: current_ratio (scale_by) reads 0, not a ratio")
