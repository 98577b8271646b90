"""Address changes before the bus: refusals, plan files and the --dry-run frames."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.address_plan import load_plan
from rtupoll.config.library import load_one
from rtupoll.errors import ConfigError, RefusedError
from rtupoll.jobs.commission import dry_run
from rtupoll.model.addressing import Change, refuse

FIXTURES = Path(__file__).parents[1] / "fixtures" / "commission"


@pytest.mark.parametrize(("pid", "new", "why"), [
    ("radar-level", 0, "broadcast"),
    ("radar-level", 248, "outside this device's range 1..247"),
    ("co2meter-an117", 0xFE, "configuration utility"),  # no method wins over the address
    ("net-irnet-pro", 5, "MT-3071 marks register 0x0016 read-only"),
    ("radar-level", 1, "already at 1"),
])
def test_refusals_that_need_no_bus(pid: str, new: int, why: str) -> None:
    with pytest.raises(RefusedError, match=why):
        refuse(Change(load_one(pid), 1, new))


def test_reserved_and_any_addresses_are_refused_with_the_profiles_reason() -> None:
    # a copy of the CO2Meter addresses on a profile that has an address method
    from dataclasses import replace

    co2 = load_one("co2meter-an117")
    radar = replace(load_one("radar-level"), addresses=co2.addresses)
    with pytest.raises(RefusedError, match="reserved: CO2Meter's proprietary protocol"):
        refuse(Change(radar, 1, 0xCC))
    with pytest.raises(RefusedError, match="'any device' address"):
        refuse(Change(radar, 1, 0xFE))


def test_dry_run_frames_match_the_manuals() -> None:
    frames = dry_run(Change(load_one("huiwen-aq"), 1, 12))
    hexes = [f for f, _ in frames]
    assert "01 03 9C 41 00 01 FA 4E" in hexes  # the manual's own "read slave address" frame
    assert hexes[2] == "01 06 9C 41 00 0C F7 8B"  # FC06 to holding 40001 (wire 0x9C41)


def test_dry_run_marks_the_byte_a_read_modify_write_keeps() -> None:
    frames = dry_run(Change(load_one("banner-ez-array"), 1, 7))
    write = next(f for f, why in frames if why.startswith("write"))
    # FC16 to 41000 (wire 0xA028): high byte kept from the read, so it and the CRC are unknown
    assert write == "01 10 A0 28 00 01 02 ?? 07 ?? ??"


def test_csv_and_yaml_plans_read_the_same() -> None:
    csv_plan = load_plan(FIXTURES / "three.csv")
    yaml_plan = load_plan(FIXTURES / "three.yaml")
    assert [(c.profile.id, c.old, c.new, c.check) for c in csv_plan] == \
        [(c.profile.id, c.old, c.new, c.check) for c in yaml_plan] == [
            ("radar-level", 1, 11, None),
            ("huiwen-aq", 2, 12, ("co2_failure", "NO_FAULT")),
            ("banner-ez-array", 3, 13, None)]
    assert csv_plan[1].where.endswith("three.csv:4")


@pytest.mark.parametrize(("name", "message", "code"), [
    ("bad-column.csv", "bad-column.csv:1: unknown column 'adress'", 2),
    ("twice.csv", "twice.csv:3: address 11 is given twice", 2),
    ("reserved.csv", "reserved.csv:3: radar-level@2 -> 0: 0 is the broadcast address", 8),
    ("unsupported.yaml", "unsupported.yaml:1: net-irnet-pro cannot be readdressed", 8),
])
def test_a_bad_plan_is_refused_with_file_and_line_before_anything_runs(
        name: str, message: str, code: int) -> None:
    with pytest.raises((ConfigError, RefusedError)) as info:
        load_plan(FIXTURES / name)
    assert message in str(info.value)
    assert info.value.exit_code == code
