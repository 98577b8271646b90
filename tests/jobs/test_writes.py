"""Writes are checked and encoded before anything is sent: the refusals and encodings."""

from __future__ import annotations

import pytest

from rtupoll.config.library import load_one
from rtupoll.errors import RefusedError, UsageError
from rtupoll.jobs.writes import RAW_FUNCTIONS, parse_value, plan_raw_write, plan_write
from rtupoll.model.raw import parse_spec

BANNER = load_one("banner-ez-array")
HUIWEN = load_one("huiwen-aq")
IRNET = load_one("net-irnet-pro")
RADAR = load_one("radar-level")


def test_enum_names_are_accepted_in_any_case_and_as_codes() -> None:
    f = BANNER.field("measurement_1_mode")
    assert parse_value(f, "tbb") == "TBB"
    assert parse_value(f, "3") == "TBB"
    with pytest.raises(RefusedError, match="not one of: DISABLED, FBB"):
        parse_value(f, "FOO")


def test_banner_has_no_fc06_so_one_register_goes_out_with_fc16() -> None:
    op = plan_write(BANNER.field("measurement_1_mode"), "TBB", BANNER.limits.functions)
    assert op.function == 16 and op.shared  # low byte of 40048: read-modify-write
    assert op.words == (0x0003,)


def test_fc06_when_the_device_has_it() -> None:
    op = plan_write(RADAR.field("baud_rate"), "9600", RADAR.limits.functions)
    assert op.function == 6 and op.words == (96,)  # scale 100


def test_a_float_field_needs_fc16() -> None:
    op = plan_write(IRNET.field("calibration_gas_level"), "50", IRNET.limits.functions)
    assert op.function == 16 and op.words == (0x0000, 0x4842)  # DCBA, the manual's frame


def test_read_only_fields_are_refused() -> None:
    with pytest.raises(RefusedError, match="co2 is read-only"):
        plan_write(HUIWEN.field("co2"), "400", HUIWEN.limits.functions)


def test_values_outside_the_documented_range_are_refused() -> None:
    with pytest.raises(RefusedError, match=r"outside the field's range 1\.0\.\.247\.0"):
        plan_write(BANNER.field("slave_address"), "248", BANNER.limits.functions)


def test_values_that_are_not_numbers_are_a_usage_error() -> None:
    with pytest.raises(UsageError, match="not a number"):
        plan_write(RADAR.field("baud_rate"), "fast", RADAR.limits.functions)


def test_values_off_the_resolution_are_refused() -> None:
    with pytest.raises(RefusedError, match="resolution"):
        plan_write(RADAR.field("baud_rate"), "9650", RADAR.limits.functions)


def test_raw_write_takes_as_many_values_as_given_and_uses_fc16_for_several() -> None:
    rw = plan_raw_write(parse_spec("holding:0x10"), "1,2,0x0A", RAW_FUNCTIONS)
    assert rw.words == (1, 2, 10) and rw.function == 16 and rw.spec.count == 3
    one = plan_raw_write(parse_spec("holding:0x10"), "7", RAW_FUNCTIONS)
    assert one.function == 6


def test_raw_write_without_fc06_uses_fc16_and_input_registers_are_refused() -> None:
    assert plan_raw_write(parse_spec("holding:40001"), "5", frozenset({3, 16})).function == 16
    with pytest.raises(RefusedError, match="read-only"):
        plan_raw_write(parse_spec("input:0"), "5", RAW_FUNCTIONS)
    with pytest.raises(RefusedError, match="outside u16"):
        plan_raw_write(parse_spec("holding:0"), "70000", RAW_FUNCTIONS)


def test_raw_write_count_must_match_the_values() -> None:
    with pytest.raises(UsageError, match="3 values expected, got 2"):
        plan_raw_write(parse_spec("holding:0:3"), "1,2", RAW_FUNCTIONS)


def test_raw_coil_write_uses_fc05() -> None:
    rw = plan_raw_write(parse_spec("coil:0xD0"), "on", RAW_FUNCTIONS)
    assert rw.function == 5 and rw.words == (1,)
