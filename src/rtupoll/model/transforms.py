"""Documented value encodings a plain type and scale cannot express (``decode:``).

Some devices store a value folded into a wider range, by a rule their manual prints.
Schneider Electric's meters (the iEM3000 series, DOCA0005EN "Power factor register
format"; the PM5300/PM5500 "PF register format") keep a four-quadrant power factor in
one Float32: a register value in -1..+1 *is* the power factor, one in -2..-1 means
``PF = -2 - value`` and one in +1..+2 means ``PF = +2 - value``. Read as a plain float,
a power factor of 0.7 in the fourth quadrant shows as 1.3: a confident wrong number.

A profile names the encoding on the field (``decode: four_quadrant_pf``); ``interpret``
unfolds the number the registers decode to (after ``scale`` and ``offset``), and
``field_words`` folds a value back (the simulator). Each encoding is one member of
``Transform``: its documented domain, its value span, and both directions. A stored
number outside the documented domain is no reading: it decodes to NaN, which every
output reports as "no value", never as a number.

Pure: no I/O.
"""

from __future__ import annotations

import enum
import math

from rtupoll.errors import EncodeError

__all__ = ["Transform"]


class Transform(str, enum.Enum):
    """One documented encoding: stored number <-> value."""

    # Schneider Electric four-quadrant power factor (DOCA0005EN, PM5xxx user manuals)
    FOUR_QUADRANT_PF = "four_quadrant_pf"

    @property
    def span(self) -> tuple[float, float]:
        """The values the encoding can give: what a field's ``range`` must lie within."""
        return (-1.0, 1.0)

    @property
    def domain(self) -> tuple[float, float]:
        """The stored numbers the document defines; any other one is no reading."""
        return (-2.0, 2.0)

    def unfold(self, stored: float) -> float:
        """The stored number (after scale and offset) -> the value the document means.

        -1..+1 is the value itself; -2..-1 is ``-2 - stored``; +1..+2 is
        ``+2 - stored``; NaN, or a number outside -2..+2, is no reading (NaN)."""
        lo, hi = self.domain
        if not math.isfinite(stored) or not lo <= stored <= hi:
            return math.nan
        if stored < -1.0:
            return round(-2.0 - stored, 9)
        if stored > 1.0:
            return round(2.0 - stored, 9)
        return stored

    def fold(self, value: float) -> float:
        """A value -> a stored number that unfolds to it (the value itself: -1..+1 is
        stored as is, in quadrants 1 and 2); a value outside the span cannot be stored."""
        lo, hi = self.span
        if not math.isfinite(value) or not lo <= value <= hi:
            raise EncodeError(f"{value:g} is outside what {self.value} holds ({lo:g}..{hi:g})")
        return value
