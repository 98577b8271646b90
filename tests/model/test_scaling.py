"""``scale_by``, pure: a field times other fields of the same device (a CT/VT-operated
meter's terminal values -> primary values), the planner reading the factors, and a
factor with no usable value leaving its fields with none."""

from __future__ import annotations

from pathlib import Path
from textwrap import dedent

import pytest

from rtupoll.config.library import load_profile
from rtupoll.model.carried import Carried, carried, carried_in
from rtupoll.model.interpret import FieldValue, field_words, interpret
from rtupoll.model.planner import decode_block, plan
from rtupoll.model.profile import Profile
from rtupoll.model.scaling import Unscaled, factors, scale, scale_values, with_factors
from rtupoll.rtu.capture import decode_stream
from rtupoll.rtu.messages import ReadReply, ReadRequest

METER = """\
id: ct-meter
vendor: ACME
kind: energy meter
model: CT1
manual: CT1 manual
addressing: pdu
limits: {max_registers: 60, max_gap: 0}
fields:
  - {name: ct, table: holding, address: 0x0006, type: u16, poll: on_request, range: [1, 9999]}
  - {name: vt, table: holding, address: 0x0007, type: u16, scale: 0.1, poll: on_request}
  - {name: current, table: holding, address: 0x200C, type: f32, scale: 0.001, unit: A,
     precision: 3, scale_by: ct}
  - {name: power, table: holding, address: 0x2012, type: f32, scale: 0.1, unit: W,
     precision: 1, scale_by: [ct, vt]}
  - {name: pulses, table: holding, address: 0x2014, type: u16, scale_by: ct}
  - {name: level, table: holding, address: 0x2015, type: u16, scale: 0.01, unit: m,
     sentinels: {0xFFFF: NOT_AVAILABLE}, scale_by: ct}
  - {name: energy, table: holding, address: 0x2016, type: f32, unit: kWh,
     scale_by: [ct, vt]}
  - {name: frequency, table: holding, address: 0x2044, type: f32, scale: 0.01, unit: Hz,
     precision: 2}
"""


@pytest.fixture
def meter(tmp_path: Path) -> Profile:
    path = tmp_path / "ct-meter.yaml"
    path.write_text(dedent(METER), encoding="utf-8")
    return load_profile(path)


def value(p: Profile, name: str, v: float | int | str) -> FieldValue:
    """What a device holding ``v`` (as its field reads it) answers, decoded."""
    f = p.field(name)
    return interpret(f, field_words(f, v))


@pytest.mark.parametrize(("amps", "ratio", "primary"), [
    (0.035, 200, 7.0), (0.001, 5, 0.005), (3.2, 1, 3.2), (1.234, 40, 49.36),
    (4.999, 3000, 14997.0), (-0.035, 200, -7.0), (0.1, 3, 0.3),
])
def test_a_current_is_multiplied_by_its_ratio_on_the_decimals_shown(
        meter: Profile, amps: float, ratio: int, primary: float) -> None:
    got = scale(value(meter, "current", amps), {"ct": value(meter, "ct", ratio)})
    assert isinstance(got, FieldValue)
    assert got.value == primary  # exactly: 0.035 x 200 is 7.0, not 7.000000000000001
    assert got.text == f"{primary:.3f}"
    assert got.raw == tuple(field_words(meter.field("current"), amps))  # the registers read


def test_power_is_multiplied_by_both_ratios(meter: Profile) -> None:
    got = scale(value(meter, "power", 723.5),
                {"ct": value(meter, "ct", 200), "vt": value(meter, "vt", 10.0)})
    assert isinstance(got, FieldValue)
    assert got.value == 1447000.0
    assert got.text == "1447000.0"


def test_a_float_without_precision_keeps_the_decimals_of_the_product(meter: Profile) -> None:
    got = scale(value(meter, "energy", 9182.44),
                {"ct": value(meter, "ct", 3), "vt": value(meter, "vt", 1.0)})
    assert isinstance(got, FieldValue) and got.value == 27547.32


def test_integers_times_integral_ratios_stay_integers(meter: Profile) -> None:
    got = scale(value(meter, "pulses", 35),
                {"ct": value(meter, "ct", 200)})
    assert isinstance(got, FieldValue) and got.value == 7000 and isinstance(got.value, int)


def test_a_ratio_of_one_changes_nothing(meter: Profile) -> None:
    fv = value(meter, "power", 1455.3)
    got = scale(fv, {"ct": value(meter, "ct", 1), "vt": value(meter, "vt", 1.0)})
    assert got == fv


def test_a_sentinel_stays_a_sentinel(meter: Profile) -> None:
    fv = value(meter, "level", "NOT_AVAILABLE")
    got = scale(fv, {"ct": value(meter, "ct", 200)})
    assert got == fv and isinstance(got, FieldValue) and got.output is None


def test_a_factor_not_read_leaves_no_value(meter: Profile) -> None:
    got = scale(value(meter, "power", 100.0), {"ct": value(meter, "ct", 200)})
    assert got == Unscaled(meter.field("power"), "vt (scale_by) was not read")


def test_a_failed_factor_read_says_why(meter: Profile) -> None:
    got = scale(value(meter, "current", 0.035), {"ct": "timeout: no reply from unit 1"})
    assert isinstance(got, Unscaled)
    assert got.reason == "ct (scale_by) not read: timeout: no reply from unit 1"


@pytest.mark.parametrize(("ratio", "why"), [
    (0, "ct (scale_by) reads 0, not a ratio"),
    (10000, "ct (scale_by) reads 10000, outside its range 1..9999"),
])
def test_a_factor_that_is_no_ratio_leaves_no_value(meter: Profile, ratio: int, why: str
                                                     ) -> None:
    got = scale(value(meter, "current", 0.035), {"ct": value(meter, "ct", ratio)})
    assert got == Unscaled(meter.field("current"), why)


def test_a_negative_or_missing_voltage_ratio_is_no_ratio(meter: Profile) -> None:
    zero = scale(value(meter, "power", 100.0),
                 {"ct": value(meter, "ct", 1), "vt": value(meter, "vt", 0.0)})
    assert isinstance(zero, Unscaled) and zero.reason == "vt (scale_by) reads 0.0, not a ratio"


def test_the_planner_reads_the_factors_with_the_fields_that_need_them(meter: Profile) -> None:
    wanted = [meter.field("current"), meter.field("frequency")]
    assert [f.name for f in factors(wanted, meter)] == ["ct"]
    assert [f.name for f in with_factors(wanted, meter)] == ["current", "frequency", "ct"]
    blocks = plan(wanted, meter)
    read = {f.name for b in blocks for f in b.fields}
    assert read == {"current", "frequency", "ct"}
    # a field without scale_by asks for nothing more
    assert {f.name for b in plan([meter.field("frequency")], meter) for f in b.fields} == \
        {"frequency"}


def test_one_read_is_scaled_whole_and_the_unscaled_are_named(meter: Profile) -> None:
    fields = [meter.field("current"), meter.field("power"), meter.field("frequency")]
    words = {"current": 0.035, "power": 723.5, "frequency": 50.0, "ct": 200, "vt": 0.0}
    got: list[FieldValue] = []
    for block in plan(fields, meter):
        regs = [0] * block.count
        for f in block.fields:
            at = f.address - block.address
            regs[at:at + f.words] = field_words(f, words[f.name])
        got += decode_block(block, regs)
    values, unscaled = scale_values(got)
    by_name = {fv.field.name: fv.value for fv in values}
    assert by_name == {"current": 7.0, "frequency": 50.0, "ct": 200, "vt": 0.0}
    assert [(u.field.name, u.reason) for u in unscaled] == \
        [("power", "vt (scale_by) reads 0.0, not a ratio")]
    # a factor the read got no value for, with why
    values, unscaled = scale_values([fv for fv in got if fv.field.name != "ct"],
                                    {"ct": "refused: exception 02"})
    assert {u.field.name for u in unscaled} == {"current", "power"}
    assert unscaled[0].reason == "ct (scale_by) not read: refused: exception 02"


def _exchange(p: Profile, start: int, values: dict[str, float | int]) -> list[Carried]:
    """``decode --profile``: one read of ``values``' fields (from ``start``), captured."""
    fields = [p.field(n) for n in values]
    count = max(f.end for f in fields) - start
    regs = [0] * count
    for f in fields:
        regs[f.address - start:f.end - start] = field_words(f, values[f.name])
    wire = ReadRequest(1, 3, start, count).frame() + ReadReply(1, 3, tuple(regs)).frame()
    _, reply = decode_stream([wire])
    return carried(reply, p)


def test_decode_scales_a_field_whose_ratio_is_in_the_same_frame(tmp_path: Path) -> None:
    path = tmp_path / "ct-meter.yaml"  # the same meter with its ratios next to the values
    path.write_text(dedent(METER).replace("0x0006", "0x2008").replace("0x0007", "0x2009"),
                    encoding="utf-8")
    near = load_profile(path)
    got = _exchange(near, 0x2008, {"ct": 200, "vt": 10.0, "current": 0.035, "power": 8.0})
    assert {c.name: (c.value, c.text) for c in got} == {
        "ct": (200, "200"), "vt": (10.0, "10.0"), "current": (7.0, "7.000 A"),
        "power": (16000.0, "16000.0 W")}


def test_decode_never_shows_a_terminal_value_as_the_reading(meter: Profile) -> None:
    (c,) = _exchange(meter, 0x200C, {"current": 0.035})
    assert c.value is None and c.severity == "warning"
    assert c.text == "0.035 A at the terminals, not scaled: ct (scale_by) was not read"
    assert c.raw == tuple(field_words(meter.field("current"), 0.035))


def test_the_product_is_taken_before_the_fields_precision(meter: Profile) -> None:
    fv = value(meter, "current", 0.0354)
    assert fv.value == 0.035  # shown at 3 decimals ...
    got = scale(fv, {"ct": value(meter, "ct", 200)})
    assert isinstance(got, FieldValue) and got.value == 7.08  # ... but 0.0354 x 200


def test_a_capture_scales_a_value_by_the_ratio_read_before_it_by_the_same_unit(
        meter: Profile) -> None:
    cur, ct = meter.field("current"), meter.field("ct")
    amps = ReadRequest(1, 3, cur.address, 2).frame() + \
        ReadReply(1, 3, tuple(list(field_words(cur, 0.035)))).frame()
    ratio = ReadRequest(1, 3, ct.address, 1).frame() + ReadReply(1, 3, (200,)).frame()
    other = ReadRequest(2, 3, ct.address, 1).frame() + ReadReply(2, 3, (5,)).frame()
    frames = decode_stream([amps, ratio, other, amps])
    found = [c for fields in carried_in(frames, meter) for c in fields if c.name == "current"]
    # the reply before any ratio: no value; after unit 1's ratio (not unit 2's): 7.0 A
    assert [c.value for c in found] == [None, None, None, 7.0]
    assert found[1].text.endswith("not scaled: ct (scale_by) was not read")
