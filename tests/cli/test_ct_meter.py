"""``scale_by`` end to end: a CHINT DTSU666 on a 200:1 current transformer (IrAt 200),
simulated, polled and read through the real CLI, shows primary values in every output;
a ratio read that fails, or reads no ratio, leaves the scaled fields with no value."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import conftest
import pytest
from cli_runner import Ran, rtupoll

from rtupoll.config.library import load_one
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
DEV = "chint-dtsu666@1"
PATIENT = (*conftest.PATIENT, "--retries", "0")
# a real meter's terminals (korneliuszm/nd45_dtsu666_converter's scan): 0.035 A at IrAt 200
CT_METER = [f"{DEV}.current_ratio=200", f"{DEV}.voltage_ratio=1.0", f"{DEV}.current_l1=0.035",
            f"{DEV}.power_l1=8.0", f"{DEV}.voltage_l1=230.7", f"{DEV}.frequency=50.0",
            f"{DEV}.import_active_energy=45.91"]


def run(*args: str) -> Ran:
    return rtupoll(*args)


def records(result: Ran) -> dict[str, dict[str, Any]]:
    return {r["field"]: r for r in map(json.loads, result.stdout.splitlines())}


def test_poll_shows_the_primary_values_of_a_ct_operated_meter(sim: Sim) -> None:
    bus = sim(DEV, sets=CT_METER, tick=None)
    result = run("poll", "-p", bus.port, *PATIENT, "--once", "--format", "json", DEV)
    assert result.returncode == 0, result.stderr
    recs = records(result)
    assert recs["current_l1"]["value"] == 7.0 and recs["current_l1"]["text"] == "7.000"
    assert recs["current_l1"]["unit"] == "A" and recs["current_l1"]["status"] == "ok"
    assert recs["power_l1"]["value"] == 1600.0  # 8.0 W x 200 x 1.0
    assert recs["import_active_energy"]["value"] == 9182.0  # 45.91 kWh x 200
    assert recs["voltage_l1"]["value"] == 230.7  # x voltage_ratio 1.0
    assert recs["frequency"]["value"] == 50.0  # not scaled
    # the registers as read stay the terminal value's
    raw = recs["current_l1"]["raw"]
    assert len(raw) == 2 and raw != [0, 0]
    assert "current_ratio" not in recs  # read for the scaling, not asked for


def test_only_the_asked_field_is_printed_and_its_ratio_is_read_with_it(sim: Sim) -> None:
    bus = sim(DEV, sets=CT_METER, tick=None)
    result = run("poll", "-p", bus.port, *PATIENT, "--once", "--format", "json",
                 "--fields", "current_l1", DEV)
    assert result.returncode == 0, result.stderr
    assert {f: r["value"] for f, r in records(result).items()} == {"current_l1": 7.0}
    asked = [w.data.hex(" ").upper() for w in bus.wire if w.direction == "in"]
    assert any(a.startswith("01 03 00 06 00 01") for a in asked), asked  # IrAt, 0x0006


def test_influx_lines_carry_the_primary_value(sim: Sim) -> None:
    bus = sim(DEV, sets=CT_METER, tick=None)
    result = run("poll", "-p", bus.port, *PATIENT, "--once", "--format", "influx",
                 "--fields", "current_l1,frequency", DEV)
    assert result.returncode == 0, result.stderr
    assert "current_l1=7" in result.stdout and "current_l1=0.035" not in result.stdout


def test_read_shows_the_primary_values(sim: Sim) -> None:
    bus = sim(DEV, sets=CT_METER, tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--format", "json", DEV, "current_l1",
                 "power_l1", "frequency")
    assert result.returncode == 0, result.stderr
    assert {f: r["value"] for f, r in records(result).items()} == \
        {"current_l1": 7.0, "power_l1": 1600.0, "frequency": 50.0}


def test_a_failed_ratio_read_leaves_the_scaled_fields_without_a_value(sim: Sim) -> None:
    # the first request of the cycle is the ratios' block (0x0006, lowest address):
    # the meter answers it with exception 04
    bus = sim(DEV, sets=CT_METER, tick=None, faults=["1:exception=4@1"])
    result = run("poll", "-p", bus.port, *PATIENT, "--once", "--format", "json", DEV)
    assert result.returncode == 9  # a device whose fields were not all read
    recs = records(result)
    for name, ratio in [("current_l1", "current_ratio"), ("power_l1", "current_ratio"),
                        ("voltage_l1", "voltage_ratio"), ("import_active_energy", "current_ratio")]:
        r = recs[name]
        assert (r["status"], r["value"], r["raw"]) == ("unscaled", None, None), r
        assert r["error"].startswith(
            f"{ratio} (scale_by) not read: exception: device 1 answered"), r["error"]
    assert recs["frequency"]["status"] == "ok" and recs["frequency"]["value"] == 50.0
    assert recs["total_power_factor"]["status"] == "ok"
    assert "unscaled: " in result.stderr and "(scale_by) not read" in result.stderr


def test_a_ratio_of_zero_is_no_ratio(sim: Sim) -> None:
    bus = sim(DEV, sets=[*CT_METER, f"{DEV}.current_ratio=0"], tick=None)
    result = run("poll", "-p", bus.port, *PATIENT, "--once", "--format", "json", DEV)
    assert result.returncode == 9
    recs = records(result)
    assert recs["current_l1"]["value"] is None and recs["current_l1"]["status"] == "unscaled"
    assert recs["current_l1"]["error"] == "current_ratio (scale_by) reads 0, not a ratio"
    assert recs["voltage_l1"]["value"] == 230.7  # its own ratio is fine


def test_read_of_a_field_whose_ratio_is_no_ratio_prints_why_and_exits_7(sim: Sim) -> None:
    bus = sim(DEV, sets=[*CT_METER, f"{DEV}.current_ratio=0"], tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--format", "json", DEV, "current_l1",
                 "frequency")
    assert result.returncode == 7
    recs = records(result)
    assert recs["current_l1"]["value"] is None
    assert recs["current_l1"]["text"] == \
        "not scaled: current_ratio (scale_by) reads 0, not a ratio"
    assert recs["frequency"]["value"] == 50.0
    assert result.stderr.strip() == ("rtupoll: unit 1: current_l1 not scaled: current_ratio "
                                     "(scale_by) reads 0, not a ratio")


@pytest.mark.parametrize("columns", ["80", "200"])
def test_profiles_show_names_the_ratios_a_field_is_multiplied_by(columns: str) -> None:
    result = rtupoll("profiles", "show", "chint-dtsu666", env={"COLUMNS": columns})
    assert result.returncode == 0, (result.stdout + result.stderr)
    out = result.stdout.splitlines()
    # every field's name whole (the ratios, a line each in the unit column, keep it narrow)
    names = [line.split()[0] for line in out if line.strip()]
    for f in load_one("chint-dtsu666").fields:
        assert f.name in names, (columns, f.name)

    def unit_lines(field: str) -> list[str]:  # the row's line and the two after it
        at = next(i for i, line in enumerate(out) if line.split()[:1] == [field])
        return out[at:at + 3]

    current, power = unit_lines("current_l1"), unit_lines("total_power")
    assert "A raw x 0.001" in current[0] and "x current_ratio" in current[1]
    assert "W raw x 0.1" in power[0]
    assert "x current_ratio" in power[1] and "x voltage_ratio" in power[2]
    assert "ratio" not in unit_lines("frequency")[0]
