"""A field's decimals, one fact: the people's display, Home Assistant's display precision
and the Prometheus metrics all take them from ``model.interpret`` (they were computed
three times, one of which gave an f64 register 0 decimals)."""

from __future__ import annotations

from pathlib import Path
from textwrap import dedent

import pytest

from rtupoll.config.library import load_library, load_profile
from rtupoll.model.interpret import (
    decimals,
    field_kind,
    field_words,
    format_value,
    interpret,
    number_decimals,
    places,
)
from rtupoll.model.profile import Field
from rtupoll.outputs.homeassistant import components
from rtupoll.outputs.metrics import field_metric


def library_fields() -> list[Field]:
    return [f for p in load_library().profiles.values() for f in p.fields]


@pytest.mark.parametrize(("x", "n"), [(0.01, 2), (0.5, 1), (10, 0), (3600.0, 0),
                                      (273.15, 2), (-0.001, 3), (1e-05, 5), (1e-10, 10),
                                      (2.5e-07, 8)])
def test_places_are_those_of_the_number_as_written(x: float, n: int) -> None:
    assert places(x) == n


def test_every_consumer_is_told_the_same_decimals() -> None:
    for field in library_fields():
        known = number_decimals(field)
        entities = components(field, controls=False)
        # a number's sensor is told its decimals; an enum, flags or text shows no number
        number = field_kind(field) == "number"
        assert not number or field.name in entities, field
        told = known if number else None
        assert entities.get(field.name, {}).get("suggested_display_precision") == told, field
        metric = field_metric(field)
        if (metric.scale, metric.offset) == (1, 0) and not (field.enum or field.flags):
            assert metric.decimals == known, field


def test_a_number_is_shown_at_its_decimals() -> None:
    shown = 0
    for field in library_fields():
        places_shown = decimals(field)
        if places_shown is None or field.enum or field.flags \
                or field.layout.type.value == "bool":
            continue
        raw = (0,) * (len(field_words(field, 0)) - 1) + (7,)  # a raw 7, whatever the order
        text = format_value(field, interpret(field, raw).value)
        assert len(text.partition(".")[2]) == places_shown, (field, text)
        shown += 1
    assert shown > 100


def test_a_float_register_without_precision_is_given_no_decimals(tmp_path: Path) -> None:
    path = tmp_path / "f.yaml"
    path.write_text(dedent("""\
        id: f
        vendor: ACME
        kind: meter
        model: F
        manual: F manual
        addressing: pdu
        fields:
          - {name: energy, table: input, address: 0, type: f64, unit: kWh}
          - {name: power, table: input, address: 4, type: f32, unit: W}
          - {name: count, table: input, address: 6, type: u32}
          - {name: volts, table: input, address: 8, type: u16, scale: 0.1, unit: V}
        """), encoding="utf-8")
    profile = load_profile(path)
    shown = {f.name: components(f, controls=False)[f.name].get("suggested_display_precision")
             for f in profile.fields}
    assert shown == {"energy": None, "power": None, "count": 0, "volts": 1}
    assert [field_metric(f).decimals for f in profile.fields] == [None, None, 0, 1]
