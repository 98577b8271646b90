"""Fields multiplied by other fields of the same device (``scale_by``).

A meter on current or voltage transformers measures at its terminals: a CHINT DTSU666
with a 200:1 current transformer holds 0.035 A where the grid carries 7.0 A, and keeps
the ratio in a register of its own (IrAt). A profile says so with ``scale_by: [ratio]``
on the field; the planner reads the factors with the fields (``with_factors``) and
``scale`` multiplies. A factor that was not read, or reads something that is not a
ratio (0, a sentinel, outside its documented range), leaves the field with no value
and a reason: never the terminal-side number as if it were the reading.

The product is taken on the decimals the two values show (0.035 x 200 is 7.0, not
7.000000000000001), the field's value before its ``precision`` (0.0354 x 200 is 7.08,
not 0.04 x 200), then rounded to the field's one precision (``decimals``).

Pure: no I/O, inputs never mutated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence

from rtupoll.frozen import frozen
from rtupoll.model.interpret import FieldValue, decimals, unrounded
from rtupoll.model.profile import Field, Profile

__all__ = ["Unscaled", "factors", "scale", "scale_values", "with_factors"]


@frozen
class Unscaled:
    """A field that has no value because one of its factors has none: why."""

    field: Field
    reason: str


def factors(fields: Iterable[Field], profile: Profile) -> tuple[Field, ...]:
    """The fields ``fields`` are scaled by and that are not among them, in profile order."""
    fields = tuple(fields)
    names = {f.name for f in fields}
    wanted = {n for f in fields for n in f.scale_by} - names
    return tuple(f for f in profile.fields if f.name in wanted)


def with_factors(fields: Sequence[Field], profile: Profile) -> tuple[Field, ...]:
    """``fields`` and, after them, the factors they need (what a read must ask for)."""
    return (*fields, *factors(fields, profile))


def scale(fv: FieldValue, got: Mapping[str, FieldValue | str]) -> FieldValue | Unscaled:
    """``fv`` times its field's factors, as read in the same cycle.

    ``got`` maps a factor's name to its value, or to why it has none (a failed read);
    a factor not in ``got`` was not read. A sentinel (the device says there is no
    reading) stays what it is: there is no number to scale.
    """
    f = fv.field
    if not f.scale_by or fv.sentinel is not None:
        return fv
    value = unrounded(f, fv.raw)  # the field's precision applies to the product
    assert isinstance(value, (int, float))  # a scaled field is a number (config.scale_by)
    for name in f.scale_by:
        factor = got.get(name)
        if factor is None:
            return Unscaled(f, f"{name} (scale_by) was not read")
        if isinstance(factor, str):
            return Unscaled(f, f"{name} (scale_by) not read: {factor}")
        why = _not_a_factor(factor)
        if why:
            return Unscaled(f, f"{name} (scale_by) {why}")
        assert isinstance(factor.value, (int, float))  # _not_a_factor said so
        value = _times(value, factor.value)
    return dataclasses.replace(fv, value=_rounded(f, value))


def scale_values(values: Sequence[FieldValue], failed: Mapping[str, str] | None = None
                 ) -> tuple[list[FieldValue], list[Unscaled]]:
    """The values of one read (factors among them), each scaled field multiplied; the
    fields that could not be are left out and returned apart, with why (``failed``: the
    fields the read got no value for, and why)."""
    got: dict[str, FieldValue | str] = dict(failed or {})
    got.update((fv.field.name, fv) for fv in values)
    out: list[FieldValue] = []
    unscaled: list[Unscaled] = []
    for fv in values:
        res = scale(fv, got)
        if isinstance(res, Unscaled):
            unscaled.append(res)
        else:
            out.append(res)
    return out, unscaled


def _not_a_factor(fv: FieldValue) -> str:
    """Why a factor's reading cannot multiply anything ("" when it can)."""
    if fv.sentinel is not None:
        return f"reads {fv.sentinel.name!r}, not a ratio"
    v = fv.value
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        return f"reads {fv.text}, not a ratio"
    f = fv.field
    lo, hi = f.minimum, f.maximum
    if lo is not None and hi is not None and not lo <= v <= hi:
        return f"reads {fv.text}, outside its range {lo:g}..{hi:g}"
    return ""


def _times(value: int | float, factor: int | float) -> int | float:
    """``value x factor`` on the decimals each shows: 0.035 x 200 = 7.0."""
    if isinstance(factor, float) and factor.is_integer():
        factor = int(factor)
    if isinstance(value, int) and isinstance(factor, int):
        return value * factor
    if not math.isfinite(value):
        return value * factor  # NaN and the infinities stay what they are (factor > 0)
    from decimal import Decimal  # here: 2 ms of import that only a scaled float needs

    return float(Decimal(repr(value)) * Decimal(repr(factor)))


def _rounded(field: Field, value: int | float) -> int | float:
    """At the field's one precision (``decimals``), as ``interpret`` gives a value."""
    places = decimals(field)
    if isinstance(value, int) or places is None or not math.isfinite(value):
        return value
    value = round(value, places)
    return int(value) if field.precision is not None and field.precision <= 0 else value
