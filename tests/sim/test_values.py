"""Simulated values move like the physical quantities they are (issue 28, item 4): a
radar's air gap and level add up to its mounting height, a room temperature drifts by
tenths of a degree, energy counters integrate the power, and a rate fault shows at once.
Values are stepped on demand (``advance``): a tick is a second of the simulator's time.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest

from rtupoll.model.planner import plan
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.engine import Engine
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import build

Sim = Callable[..., SimulatedBus]


def number(bus: SimulatedBus, unit: int, field: str) -> float:
    value = bus.get(unit, field).value
    assert isinstance(value, (int, float))
    return float(value)


def test_the_radars_air_gap_and_level_add_up_to_its_mounting_height(sim: Sim) -> None:
    bus = sim("radar-level@2", tick=None)
    height = number(bus, 2, "air_gap_cm") + number(bus, 2, "level_cm")
    levels = []
    for _ in range(120):
        bus.advance(5)
        gap, level = number(bus, 2, "air_gap_cm"), number(bus, 2, "level_cm")
        assert abs(gap + level - height) <= 1  # cm: each is rounded on its own
        assert abs(number(bus, 2, "air_gap_mm") + number(bus, 2, "level_mm")
                   - 10 * height) <= 15
        levels.append(level)
    assert len(set(levels)) > 5  # the level moves ...
    steps = [abs(b - a) for a, b in itertools.pairwise(levels)]
    assert max(steps) < 50  # ... as water does: centimetres in five seconds, not metres
    bus.set(2, "level_cm", 300)  # pinned, the air gap follows
    assert number(bus, 2, "air_gap_cm") == pytest.approx(height - 300, abs=1)


def test_a_room_temperature_in_kelvin_drifts_by_tenths_of_a_degree(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    seen = []
    for _ in range(360):  # an hour, every 10 s
        bus.advance(10)
        seen.append(number(bus, 1, "temperature"))
    assert min(seen) >= 291 and max(seen) <= 299  # a room: 18-26 °C
    assert max(seen) - min(seen) < 2.0  # was 7-27 °C within minutes
    assert len(set(seen)) > 10  # and it is alive


def test_a_charging_epever_says_it_is_charging(sim: Sim) -> None:
    bus = sim("epever-tracer@2", tick=None)
    for _ in range(60):  # ten minutes, every 10 s: the states' own episodes come and go
        bus.advance(10)
        if number(bus, 2, "charging_current") > 0 and bus.get(2, "charging_fault").text \
                == "NORMAL":
            assert bus.get(2, "running").text == "RUNNING"
            assert bus.get(2, "charging_state").text in ("FLOAT", "BOOST", "EQUALIZATION")


def test_energy_counters_integrate_the_power(sim: Sim) -> None:
    bus = sim("eastron-sdm630@1", tick=None)
    start = {f: number(bus, 1, f) for f in ("import_active_energy", "export_active_energy",
                                             "total_active_energy")}
    powers = []
    for _ in range(60):  # an hour in minutes
        powers.append(number(bus, 1, "total_power"))
        bus.advance(60)
    kwh = sum(powers) / len(powers) / 1000  # kW for one hour
    grew = {f: number(bus, 1, f) - v for f, v in start.items()}
    assert grew["import_active_energy"] == pytest.approx(kwh, rel=0.02)  # ~3.1 kWh
    assert grew["total_active_energy"] == pytest.approx(kwh, rel=0.02)
    assert grew["export_active_energy"] == 0  # nothing fed back under a load


def test_a_rate_fault_shows_within_its_first_one_over_rate_requests() -> None:
    engine = Engine(build(["huiwen-aq@3"], faults=["3:crc@20%"]).devices, tick=None)
    d = engine.devices[0]
    request = next(ReadRequest(3, b.table.read_function, b.address, b.count).frame()
                   for b in plan(d.profile.default_fields(), d.profile))
    notes = [tx.notes for _ in range(5) for tx in engine.handle(request)]
    assert any("crc" in n for n in notes), notes  # the default seed's first draw was #23
    more = [tx.notes for _ in range(995) for tx in engine.handle(request)]
    rate = sum("crc" in n for n in notes + more) / 1000
    assert 0.15 < rate < 0.25  # still the rate asked for
