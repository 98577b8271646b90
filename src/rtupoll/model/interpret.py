"""A field's registers, interpreted: value, enum name or active flags, and severity.

The one place where a profile's meaning (enums, flags, severities, units) is
applied to decoded numbers; the CLI tables, JSON/CSV sinks and the simulator all
go through ``interpret`` / ``field_words`` so they agree.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from rtupoll.frozen import frozen
from rtupoll.model.codec import (
    DataType,
    Value,
    active_flags,
    decode,
    decode_raw,
    encode,
    encode_raw,
    enum_code,
    enum_name,
    flags_mask,
    short_f32,
)
from rtupoll.model.profile import Choice, Field, Severity


@frozen
class FieldValue:
    """One decoded field."""

    field: Field
    value: Value  # number, text, enum name, or list of active flag names
    raw: tuple[int, ...]  # the registers as read
    code: int | None = None  # the integer behind an enum or flags field
    severity: Severity = Severity.OK
    # the stored value is one of the field's sentinels ("not available", "sensor error"):
    # ``value`` then holds what the registers decode to, which is not a reading
    sentinel: Choice | None = None

    @property
    def present(self) -> bool:
        """A real reading (not a sentinel)."""
        return self.sentinel is None

    @property
    def output(self) -> Value | None:
        """The value outputs should publish: None when the device says there is none."""
        return None if self.sentinel is not None else self.value

    @property
    def text(self) -> str:
        if self.sentinel is not None:
            return self.sentinel.name
        return format_value(self.field, self.value)


def interpret(field: Field, words: Sequence[int]) -> FieldValue:
    """Registers -> meaning. Unknown enum codes and undocumented flag bits stay visible;
    a sentinel is reported by its name, never as a number."""
    raw = tuple(words)
    if field.sentinels:
        stored = decode_raw(raw, field.layout)
        if isinstance(stored, (int, float)) and not isinstance(stored, bool):
            choice = field.sentinels.get(stored)
            if choice is not None:
                return FieldValue(field, decode(raw, field.layout), raw, None,
                                  choice.severity, choice)
    value = _rounded(field, raw)
    if field.enum and isinstance(value, int):
        choice = field.enum.get(value)
        name = choice.name if choice is not None else \
            f"{field.other.name} ({value})" if field.other else enum_name(value, {})
        return FieldValue(field, name, raw, value,
                          reading_severity(name, severities(field), unlisted_severity(field)))
    if field.flags and isinstance(value, int):
        names = active_flags(value, {m: c.name for m, c in field.flags.items()})
        return FieldValue(field, names, raw, value,
                          reading_severity(names, severities(field), Severity.WARNING))
    return FieldValue(field, value, raw)


_SEVERITIES: dict[int, tuple[Field, dict[str, Severity]]] = {}  # id(field) -> its names'


def severities(field: Field) -> Mapping[str, Severity]:
    """Each name an enum or flags field's reading can hold (its enum values', its
    flags'), with its severity in the profile; empty for any other field. What a fleet
    viewer is told in ``bridge/info`` (outputs.fleet) to colour readings as the
    dashboard does (``reading_severity``)."""
    got = _SEVERITIES.get(id(field))
    if got is None or got[0] is not field:
        if len(_SEVERITIES) > 100_000:  # profiles reloaded again and again: start afresh
            _SEVERITIES.clear()
        got = _SEVERITIES[id(field)] = (field, {
            c.name: c.severity for c in (*field.enum.values(), *field.flags.values())})
    return got[1]


def unlisted_severity(field: Field) -> Severity:
    """The severity of a name ``severities`` does not list: an enum code the manual
    does not list (``unknown (9)``) or the catch-all's (``other:``, its severity), an
    undocumented flag bit (``bit 3``): warning, but for a catch-all's own."""
    return field.other.severity if field.enum and field.other else Severity.WARNING


def reading_severity(value: object, named: Mapping[str, Severity], unlisted: Severity
                     ) -> Severity:
    """The one rule for a reading's severity, from the names it holds (an enum's value,
    or one flag's: a str; a flag set's active names: a list): each name's in ``named``
    (``severities``), ``unlisted`` for a name not there (``unlisted_severity``); a flag
    set's is its worst name's, ok with none set. ``interpret``, the dashboard's badges
    and the fleet page (from ``bridge/info`` and a state message) all go by it."""
    worst = Severity.OK
    for name in value if isinstance(value, list) else (value,):
        sev = named.get(name, unlisted) if isinstance(name, str) else unlisted
        if sev.rank > worst.rank:
            worst = sev
    return worst


def field_words(field: Field, value: Value, current: Sequence[int] | None = None
                ) -> tuple[int, ...]:
    """Meaning -> registers: enum names, flag name lists, sentinel names or numbers.
    Inverse of ``interpret``."""
    if field.sentinels and isinstance(value, str):
        for stored, choice in field.sentinels.items():
            if choice.name == value:
                return encode_raw(stored, field.layout, current)
    if field.transform is not None and isinstance(value, (int, float)) \
            and not isinstance(value, bool):
        value = field.transform.fold(float(value))
    if field.enum and isinstance(value, str):
        value = enum_code(value, {c: ch.name for c, ch in field.enum.items()})
    elif field.flags and isinstance(value, list):
        value = flags_mask(value, {m: ch.name for m, ch in field.flags.items()})
    if isinstance(value, list):
        raise TypeError(f"{field.name} has no flags")
    return encode(value, field.layout, current)


def unrounded(field: Field, words: Sequence[int]) -> Value:
    """The decoded value, a float at the precision its type carries (an f32 296.15 is
    296.15, not 296.1499938964844), before the field's ``precision``: what a ``scale_by``
    ratio multiplies (0.0354 kWh x 200 is 7.08, not 0.04 x 200); unfolded by the field's
    ``decode:`` encoding when it has one (model.transforms)."""
    layout = field.layout
    value: Value
    if layout.type is DataType.F32:  # decoded once: the stored float, at its own precision
        stored = short_f32(float(decode_raw(words, layout)))
        value = round(stored * layout.scale + layout.offset, 9) if layout.scaled else stored
    else:
        value = decode(words, layout)
    if field.transform is not None and isinstance(value, (int, float)) \
            and not isinstance(value, bool):
        return field.transform.unfold(float(value))
    return value


def _rounded(field: Field, words: tuple[int, ...]) -> Value:
    """The decoded value (``unrounded``), then at the field's ``precision`` when it has one."""
    value = unrounded(field, words)
    if not isinstance(value, float) or not math.isfinite(value):
        return value
    if field.precision is not None and math.isfinite(value):
        value = round(value, field.precision)
        if field.precision <= 0:
            return int(value)
    return value


def places(x: float) -> int:
    """Decimal places a number has as written: 0.01 -> 2, 273.15 -> 2, 3600 -> 0,
    1e-05 -> 5."""
    text = repr(float(abs(x)))
    if "e" in text:
        mantissa, _, exponent = text.partition("e")
        return max(0, places(float(mantissa)) - int(exponent))
    return len(text.partition(".")[2].rstrip("0"))


def decimals(field: Field) -> int | None:
    """The one number of decimal places a field is shown at, in every output: its
    profile's ``precision``; for a scaled integer type, what its scale and offset carry
    (a u16 with scale 0.01 is 11.80, never 11.8 one scan and 11.77 the next); None for
    an unscaled integer (its value is an int) and for a float without a precision
    (shown at the precision the type carries)."""
    if field.precision is not None:
        return max(field.precision, 0)
    layout = field.layout
    if layout.type.is_integer and layout.scaled:
        return max(places(layout.scale), places(layout.offset))
    return None


def number_decimals(field: Field) -> int | None:
    """The decimals a field's numbers really have, for a consumer told them once (Home
    Assistant's display precision, the metrics' rounding): ``decimals``, 0 for an
    unscaled integer; None for a float type without a precision (its digits are its
    own)."""
    known = decimals(field)
    return 0 if known is None and field.layout.type.is_integer else known


KINDS = ("number", "enum", "flags", "text")  # a field's kind on a screen (``field_kind``)


def field_kind(field: Field) -> str:
    """What sort of value a field has on a screen: ``number``, ``enum``, ``flags`` or
    ``text`` (a string, and a coil's true/false). Only numbers have trends; the dashboard,
    a fleet viewer's ``bridge/info`` and Home Assistant's entities all go by it."""
    if field.enum:
        return "enum"
    if field.flags:
        return "flags"
    if field.layout.type in (DataType.STRING, DataType.BOOL):
        return "text"
    return "number"


def shown_precision(field: Field) -> int | None:
    """The decimals a screen is told a field's numbers have (the dashboard's and a fleet
    viewer's ``precision``, Home Assistant's display precision): ``number_decimals``;
    None for what is not a number (``field_kind``) and for a float register without a
    precision."""
    return number_decimals(field) if field_kind(field) == "number" else None


# units shown in another unit on a person's screen: unit -> (shown unit, offset added)
DISPLAY_UNITS = {"K": ("°C", -273.15)}


def display_unit(field: Field, *, celsius: bool = True) -> str:
    """The unit a field is shown in to a person (``display``), with or without a value."""
    shown = DISPLAY_UNITS.get(field.unit)
    return shown[0] if celsius and shown is not None else field.unit


def shown_number(unit: str, value: float, places: int | None, *,
                 difference: bool = False) -> float:
    """A number of ``unit`` in the unit a person is shown it in (``DISPLAY_UNITS``: a
    temperature in kelvin in °C), at ``places`` decimals (None: as it comes, to 6). A
    difference moves by no offset: 1.5 K of correction is 1.5 °C. The one rule behind
    the live table, ``read``'s table, the dashboard and ``/api/state``."""
    shown = DISPLAY_UNITS.get(unit)
    if shown is None or not math.isfinite(value):
        return value
    moved = value if difference else value + shown[1]
    return round(moved, places if places is not None else 6)


def display_value(fv: FieldValue, *, celsius: bool = True) -> tuple[Value, str, str]:
    """A reading as a person reads it: (value, text, unit). A temperature in kelvin is
    shown in °C (what Home Assistant and the Prometheus metrics show too) at the same
    decimals; records and outputs keep the device's unit, and say it."""
    field = fv.field
    value = fv.value
    if celsius and field.unit in DISPLAY_UNITS and fv.present \
            and isinstance(value, (int, float)) and not isinstance(value, bool) \
            and math.isfinite(value):
        places = decimals(field)
        moved = shown_number(field.unit, value, places, difference=field.difference)
        return (moved, f"{moved:.{places}f}" if places is not None else f"{moved:g}",
                DISPLAY_UNITS[field.unit][0])
    return value, fv.text, field.unit


def display(fv: FieldValue, *, celsius: bool = True) -> tuple[str, str]:
    """A reading as a person reads it: (text, unit) (``display_value``)."""
    _, text, unit = display_value(fv, celsius=celsius)
    return text, unit


def format_value(field: Field, value: Value) -> str:
    """For people: numbers at the field's one precision (``decimals``), else floats at
    the precision the type carries; flags joined."""
    if isinstance(value, list):
        return ", ".join(value) if value else "none"
    places = decimals(field)
    if places is not None and isinstance(value, (int, float)) and not isinstance(value, bool) \
            and math.isfinite(value) and (isinstance(value, float) or places > 0) \
            and not field.enum and not field.flags:
        return f"{value:.{places}f}"
    if isinstance(value, float):
        if field.layout.type is DataType.F32 and math.isfinite(value):
            # the value is already the shortest decimal for its f32: print it positional
            # (an f32 energy total of 35565090 Wh, not 3.556509e+07)
            text = repr(value)
            if "e" not in text:
                return text[:-2] if text.endswith(".0") else text
        digits = 7 if field.layout.type is DataType.F32 else 10
        return f"{value:.{digits}g}"
    return str(value)
