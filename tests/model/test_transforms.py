"""``decode:`` encodings, pure: the four-quadrant power factor of Schneider meters unfolded
as the vendor's table says, after scale and offset, folded back for the simulator, and a
stored number outside the documented domain giving no reading."""

from __future__ import annotations

import json
import math
from pathlib import Path
from textwrap import dedent

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_profile
from rtupoll.errors import EncodeError
from rtupoll.model.codec import encode_raw
from rtupoll.model.interpret import field_words, interpret
from rtupoll.model.profile import Profile
from rtupoll.model.transforms import Transform

PF = Transform.FOUR_QUADRANT_PF

METER = """\
id: pf-meter
vendor: ACME
kind: energy meter
model: PF1
manual: PF1 manual
addressing: pdu
fields:
  - {name: pf, table: holding, address: 0, type: f32, precision: 3, decode: four_quadrant_pf}
  - {name: pf_int, table: holding, address: 2, type: i16, scale: 0.001,
     decode: four_quadrant_pf}
  - {name: pf_flagged, table: holding, address: 3, type: i16, scale: 0.001,
     decode: four_quadrant_pf, sentinels: {0x7FFF: NOT_AVAILABLE}}
  - {name: plain, table: holding, address: 5, type: f32, precision: 3}
"""


@pytest.fixture
def meter(tmp_path: Path) -> Profile:
    path = tmp_path / "pf-meter.yaml"
    path.write_text(dedent(METER), encoding="utf-8")
    return load_profile(path)


@pytest.mark.parametrize(("stored", "value"), [
    (0.0, 0.0), (0.85, 0.85), (1.0, 1.0),            # quadrant 1: the value itself
    (-0.85, -0.85), (-1.0, -1.0),                    # -1..0: the value itself
    (-1.3, -0.7), (-2.0, 0.0), (-1.05, -0.95),       # -2..-1: -2 - stored
    (1.3, 0.7), (2.0, 0.0), (1.05, 0.95),            # +1..+2: +2 - stored
])
def test_the_stored_number_unfolds_as_the_vendors_table_says(stored: float, value: float
                                                             ) -> None:
    assert PF.unfold(stored) == pytest.approx(value, abs=1e-9)


@pytest.mark.parametrize("stored", [2.0001, -2.5, 7.0, math.inf, -math.inf, math.nan])
def test_a_number_outside_the_documented_domain_is_no_reading(stored: float) -> None:
    assert math.isnan(PF.unfold(stored))


def test_folding_gives_a_stored_number_that_unfolds_to_the_value() -> None:
    for v in (-1.0, -0.7, 0.0, 0.5, 0.95, 1.0):
        assert PF.unfold(PF.fold(v)) == v
    for v in (1.2, -1.01, math.nan):
        with pytest.raises(EncodeError, match="outside what four_quadrant_pf holds"):
            PF.fold(v)


def test_a_float_register_is_unfolded_at_its_precision(meter: Profile) -> None:
    f = meter.field("pf")
    fourth = interpret(f, encode_raw(1.3, f.layout))  # a plain read would say 1.3
    assert fourth.value == 0.7 and fourth.text == "0.700"
    third = interpret(f, encode_raw(-1.05, f.layout))
    assert third.value == -0.95
    plain = meter.field("plain")  # the same registers without decode: the code as stored
    assert interpret(plain, encode_raw(1.3, plain.layout)).value == 1.3


def test_an_integer_register_is_unfolded_after_its_scale(meter: Profile) -> None:
    f = meter.field("pf_int")
    assert interpret(f, (1300,)).value == 0.7  # 1300 x 0.001 = 1.3 -> +2 - 1.3
    assert interpret(f, ((-1300) & 0xFFFF,)).value == -0.7
    assert interpret(f, (950,)).value == 0.95
    assert math.isnan(float(interpret(f, (2500,)).value))  # 2.5: outside -2..+2


def test_a_sentinel_stays_a_sentinel(meter: Profile) -> None:
    fv = interpret(meter.field("pf_flagged"), (0x7FFF,))  # 32.767: no reading, named
    assert fv.sentinel is not None and fv.text == "NOT_AVAILABLE" and fv.output is None


def test_field_words_fold_and_interpret_unfolds_to_the_same_value(meter: Profile) -> None:
    for name in ("pf", "pf_int"):
        f = meter.field(name)
        for v in (-1.0, -0.5, 0.0, 0.7, 1.0):
            assert interpret(f, field_words(f, v)).value == pytest.approx(v, abs=1e-9)
        with pytest.raises(EncodeError):
            field_words(f, 1.3)  # a power factor above 1 is no value to store


def test_a_decoded_field_without_a_range_gets_the_encodings_span(meter: Profile) -> None:
    f = meter.field("pf")
    assert (f.minimum, f.maximum) == PF.span == (-1.0, 1.0)
    assert f.transform is PF and meter.field("plain").transform is None


def test_a_code_outside_the_table_decodes_to_no_value() -> None:
    """Register 3084 of the bundled iEM3155 holding 3.0 (no quadrant of the vendor's
    table): ``decode`` gives no value, never 3.0 or -1.0 as a power factor."""
    frames = "01 03 0c 0b 00 02 b6 99 01 03 04 40 40 00 00 ee 27"
    out = rtupoll("decode", "--profile", "schneider-iem3155", "--format",
                  "json", frames)
    assert out.returncode == 0, (out.stdout + out.stderr)
    (field,) = json.loads(out.stdout.splitlines()[-1])["fields"]
    assert field["field"] == "total_power_factor" and field["value"] is None
    assert field["text"] == "NaN" and field["raw"] == [0x4040, 0]
