"""``JsonRecords``: ``poll``'s JSON lines from pre-encoded fragments are byte for byte the
records ``to_json(reading_record(r))`` makes, for every field of every bundled profile,
whatever its registers hold (sentinels, enums, flags, NaN and infinities, text); NaN and
infinities as JSON nulls and empty CSV cells (rtupoll.ui.records)."""

from __future__ import annotations

import dataclasses
import functools
import json

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from rtupoll.config.library import load_library
from rtupoll.config.site import DeviceConfig, from_specs
from rtupoll.jobs.stats import Reading, Status
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Field
from rtupoll.model.record import finite, nonfinite_text
from rtupoll.ui.records import CsvWriter, JsonRecords, json_safe, reading_record, to_json


@functools.cache
def _devices() -> tuple[tuple[DeviceConfig, Field], ...]:
    """Every field of every bundled profile, on a device of that profile."""
    out = []
    for pid, profile in sorted(load_library().profiles.items()):
        site = from_specs("/dev/null", [(pid, 7)], check_serial=False)
        (_, device), = site.devices()
        out += [(device, f) for f in profile.fields]
    return tuple(out)


def _expected(r: Reading) -> str:
    return to_json(reading_record(r)) + "\n"


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(pick=st.integers(min_value=0), words=st.lists(st.integers(0, 0xFFFF), min_size=4,
                                                    max_size=4),
       when=st.floats(min_value=0, max_value=4e9))
@example(pick=0, words=[0x7FC0, 0, 0, 0], when=1.7e9)  # NaN in a float field
@example(pick=0, words=[0x7F80, 0, 0, 0], when=1.7e9)  # +inf
@example(pick=0, words=[0xFF80, 0, 0, 0], when=1.0005)  # -inf; a time on a rounding edge
def test_a_value_read_is_the_same_line_as_the_general_record(pick: int, words: list[int],
                                                           when: float) -> None:
    fields = _devices()
    floats = [pair for pair in fields if pair[1].layout.type.value == "f32"]
    records = JsonRecords()
    for device, field in (fields[pick % len(fields)], floats[pick % len(floats)]):
        fv = interpret(field, (words + [0] * field.words)[:field.words])  # strings: longer
        r = Reading(when, device, field, fv, Status.OK)
        assert records.line(r) == _expected(r)
        assert records.line(r) == _expected(r)  # the fragments' second use


def test_every_field_of_every_profile_at_zero_and_all_ones() -> None:
    records = JsonRecords()
    for device, field in _devices():
        for word in (0, 1, 0x7FFF, 0x8000, 0xFFFF):
            r = Reading(1_700_000_000.123456, device, field,
                        interpret(field, [word] * field.words), Status.OK)
            assert records.line(r) == _expected(r), field.name


def test_failed_and_absent_readings_are_the_general_record() -> None:
    records = JsonRecords()
    device, field = _devices()[0]
    for status, error in ((Status.TIMEOUT, "no response from x@7"), (Status.ABSENT, "not in 1"),
                          (Status.SKIPPED, "not read: \"x\" stopped answering"),
                          (Status.GARBLED, "CRC error"), (Status.PORT, "/dev/x went away")):
        r = Reading(1_700_000_000.5, device, field, None, status, error)
        assert records.line(r) == _expected(r)


@given(name=st.text(min_size=1, max_size=12), unit=st.text(max_size=6))
def test_names_and_units_are_escaped_as_the_encoder_escapes_them(name: str, unit: str) -> None:
    """Quotes, backslashes, control characters, non-ASCII: JSON escaping is the encoder's."""
    device, field = _devices()[0]
    device = dataclasses.replace(device, name=name)
    field = dataclasses.replace(field, unit=unit)
    r = Reading(1_700_000_000.0, device, field, interpret(field, [1] * field.words), Status.OK)
    assert JsonRecords().line(r) == _expected(r)


def test_a_device_renamed_or_moved_gets_new_fragments() -> None:
    """A reload that renames a device or moves it to another address: the next line says
    so (the fragments are keyed by what they spell, not by the object)."""
    records = JsonRecords()
    device, field = _devices()[0]
    fv = interpret(field, [1] * field.words)
    first = records.line(Reading(1.0, device, field, fv, Status.OK))
    moved = dataclasses.replace(device, name="boiler", address=9)
    second = records.line(Reading(1.0, moved, field, fv, Status.OK))
    assert '"device":"boiler"' in second and '"address":9' in second
    assert second == _expected(Reading(1.0, moved, field, fv, Status.OK)) != first


@given(words=st.lists(st.integers(0, 3), min_size=2, max_size=30))
def test_a_field_read_again_and_again_says_each_readings_own_value(words: list[int]) -> None:
    """One writer, one field, values that repeat and change back (the value's part is
    kept while the reading stays the same): every line is that reading's record."""
    records = JsonRecords()
    pairs = [p for p in _devices() if p[1].words == 1][:3]
    for i, word in enumerate(words):
        device, field = pairs[i % len(pairs)]
        r = Reading(1_700_000_000.0 + i, device, field, interpret(field, [word]), Status.OK)
        assert records.line(r) == _expected(r)


def test_a_field_redefined_by_a_reload_reads_anew_from_the_same_registers() -> None:
    """The same registers, the field's scale changed (a reload of its profile): the new
    value, not the line kept for the old definition."""
    records = JsonRecords()
    device, field = next(p for p in _devices() if p[1].words == 1
                         and p[1].layout.type.value == "u16" and not p[1].enum
                         and not p[1].flags and not p[1].sentinels)
    before = Reading(1.0, device, field, interpret(field, [100]), Status.OK)
    rescaled = dataclasses.replace(field, layout=dataclasses.replace(field.layout, scale=0.5))
    after = Reading(1.0, device, rescaled, interpret(rescaled, [100]), Status.OK)
    assert records.line(before) == _expected(before)
    assert records.line(after) == _expected(after) != _expected(before)


def test_finite_and_json_safe_turn_nan_and_inf_into_null() -> None:
    assert finite(float("nan")) is None and finite(float("-inf")) is None
    assert finite(1.5) == 1.5 and finite("NaN") == "NaN"
    assert [nonfinite_text(v) for v in (float("nan"), float("inf"), float("-inf"), 1.0)] == \
        ["NaN", "+inf", "-inf", None]
    nested = {"a": [float("nan"), {"b": float("inf")}], "c": (1, float("-inf"))}
    assert json_safe(nested) == {"a": [None, {"b": None}], "c": [1, None]}
    line = to_json({"value": float("nan"), "raw": [1, 2]})
    assert json.loads(line, parse_constant=lambda c: pytest.fail(f"bare {c}")) == \
        {"value": None, "raw": [1, 2]}


def test_csv_cells_of_nan_are_empty() -> None:
    import io

    out = io.StringIO()
    CsvWriter(out, ("value", "text")).write({"value": float("nan"), "text": "NaN"})
    assert out.getvalue().splitlines() == ["value,text", ",NaN"]
