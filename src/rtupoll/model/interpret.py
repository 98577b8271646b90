"""A field's registers, interpreted: value, enum name or active flags, and severity.

The one place where a profile's meaning (enums, flags, severities, units) is
applied to decoded numbers; the CLI tables, JSON/CSV sinks and the simulator all
go through ``interpret`` / ``field_words`` so they agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from rtupoll.model.codec import (
    DataType,
    Value,
    active_flags,
    decode,
    encode,
    enum_code,
    enum_name,
    flags_mask,
)
from rtupoll.model.profile import Field, Severity


@dataclass(frozen=True)
class FieldValue:
    """One decoded field."""

    field: Field
    value: Value  # number, text, enum name, or list of active flag names
    raw: tuple[int, ...]  # the registers as read
    code: int | None = None  # the integer behind an enum or flags field
    severity: Severity = Severity.OK

    @property
    def text(self) -> str:
        return format_value(self.field, self.value)


def interpret(field: Field, words: Sequence[int]) -> FieldValue:
    """Registers -> meaning. Unknown enum codes and undocumented flag bits stay visible."""
    raw = tuple(words)
    value = decode(raw, field.layout)
    if field.enum and isinstance(value, int):
        choice = field.enum.get(value)
        if choice is None:
            if field.other:
                other = field.other
                return FieldValue(field, f"{other.name} ({value})", raw, value, other.severity)
            return FieldValue(field, enum_name(value, {}), raw, value, Severity.WARNING)
        return FieldValue(field, choice.name, raw, value, choice.severity)
    if field.flags and isinstance(value, int):
        names = active_flags(value, {m: c.name for m, c in field.flags.items()})
        sev = max((c.severity for m, c in field.flags.items() if m and value & m == m),
                  key=lambda s: s.rank, default=Severity.OK)
        if any(n.startswith("bit ") for n in names):
            sev = max(sev, Severity.WARNING, key=lambda s: s.rank)
        return FieldValue(field, names, raw, value, sev)
    return FieldValue(field, value, raw)


def field_words(field: Field, value: Value, current: Sequence[int] | None = None
                ) -> tuple[int, ...]:
    """Meaning -> registers: enum names, flag name lists or numbers. Inverse of ``interpret``."""
    if field.enum and isinstance(value, str):
        value = enum_code(value, {c: ch.name for c, ch in field.enum.items()})
    elif field.flags and isinstance(value, list):
        value = flags_mask(value, {m: ch.name for m, ch in field.flags.items()})
    if isinstance(value, list):
        raise TypeError(f"{field.name} has no flags")
    return encode(value, field.layout, current)


def format_value(field: Field, value: Value) -> str:
    """For people: floats to the precision the type carries, flags joined."""
    if isinstance(value, list):
        return ", ".join(value) if value else "none"
    if isinstance(value, float):
        digits = 7 if field.layout.type is DataType.F32 else 10
        return f"{value:.{digits}g}"
    return str(value)
