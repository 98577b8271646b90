"""From one value a person reads off the device, the register settings that give it.

Pure. A technician usually knows one true value (the meter's display shows 231.4 V)
and tries byte orders and offsets by hand; an off-by-one in the manual's numbering is
then easily taken for a byte order. This searches every setting a profile can state
for a number -- where it starts (up to ``REACH`` registers either side of where the
manual says, which covers 0- and 1-based numbering), its type, its byte and word
order, a decimal scale -- and keeps those that give the known value to the precision
it was written with (``231.4``: within 0.05).

The ones kept are ranked: the address as given before an offset, a float unscaled or
an integer with a decimal scale (how meters store numbers) before the unusual, and
the plain orders before the swapped ones only as a tie-break. Several settings giving
the value is normal (a float and an integer can both hit 231.4); the ranking says
which a register map most likely uses, and a second known value decides.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from decimal import Decimal, InvalidOperation

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.model.codec import ByteOrder, DataType, Layout, decode_raw

REACH = 2  # registers before and after the given address a value may start at
SCALES = tuple(10.0 ** k for k in range(-4, 4))  # 0.0001 .. 1000
TYPES = (DataType.U16, DataType.I16, DataType.U32, DataType.I32, DataType.F32, DataType.F64)
ORDERS_16 = (ByteOrder.ABCD, ByteOrder.BADC)  # a 16-bit register: as sent, or bytes swapped


@frozen
class Known:
    """A value as a person read it: the number, and how precisely it was written."""

    value: float
    tolerance: float  # half a unit of its last written digit
    places: int = 0  # decimals as written: what a reading is shown with

    def matches(self, got: float) -> bool:
        return abs(got - self.value) <= self.tolerance * (1 + 1e-9)


def parse_known(text: str) -> Known:
    """``231.4`` (within 0.05), ``-12`` (within 0.5), ``1.5e3`` (within 50)."""
    try:
        number = Decimal(text.strip())
    except InvalidOperation:
        raise UsageError(f"--known {text!r}: expected a number as the device shows it, "
                         "e.g. 231.4") from None
    if not number.is_finite():
        raise UsageError(f"--known {text!r}: expected a finite number")
    exponent = number.as_tuple().exponent
    assert isinstance(exponent, int)
    return Known(float(number), 0.5 * 10.0 ** exponent, max(0, -exponent))


@frozen
class Solution:
    """One setting that gives the known value."""

    address: int  # wire address of the first register
    offset: int  # registers from the address asked about (- before, + after)
    type: DataType
    order: ByteOrder
    scale: float
    words: tuple[int, ...]
    value: float  # what the setting reads (scaled)
    score: float
    places: int = 0  # decimals of the known value

    @property
    def setting(self) -> str:
        """The profile field's keys that read it this way."""
        parts = [f"address: 0x{self.address:04X}", f"type: {self.type.value}"]
        if self.type.words > 1 or self.order is not ByteOrder.ABCD:
            parts.append(f"order: {self.order.value}")
        if self.scale != 1:
            parts.append(f"scale: {_number(self.scale)}")
        return ", ".join(parts)

    @property
    def text(self) -> str:
        return f"{self.value:.{self.places}f}"


def solve(words: Sequence[int], first: int, address: int, known: Known) -> list[Solution]:
    """Every setting of ``words`` (read from wire ``first``) that gives ``known``, starting
    within ``REACH`` of ``address``; the likeliest first."""
    ws = tuple(w & 0xFFFF for w in words)
    found: list[Solution] = []
    for start in range(max(first, address - REACH), address + REACH + 1):
        i = start - first
        for dtype, order in _layouts():
            n = dtype.words
            if i < 0 or i + n > len(ws):
                continue
            raw = decode_raw(ws[i : i + n], Layout(dtype, n, order))
            assert isinstance(raw, (int, float)) and not isinstance(raw, bool)
            if isinstance(raw, float) and not math.isfinite(raw):
                continue
            for scale in SCALES:
                got = raw * scale
                if known.matches(got):
                    score = _score(dtype, order, scale, start - address, raw)
                    found.append(Solution(start, start - address, dtype, order, scale,
                                          ws[i : i + n], got, score, known.places))
    return sorted(_distinct(found), key=lambda s: (-s.score, abs(s.offset), s.type.words))


def _layouts() -> Iterator[tuple[DataType, ByteOrder]]:
    for dtype in TYPES:
        for order in ORDERS_16 if dtype.words == 1 else tuple(ByteOrder):
            yield dtype, order


def _score(dtype: DataType, order: ByteOrder, scale: float, offset: int,
           raw: int | float) -> float:
    score = 1.0 - 0.15 * abs(offset)  # the address as the manual gives it, first
    if dtype.is_float:
        score -= 0.0 if scale == 1 else 0.3  # a float is stored as the value itself
        if raw and not 1e-6 < abs(raw) < 1e9:
            score -= 0.4  # an exponent no device reports: a coincidence of bits
    else:
        score -= 0.05 * abs(round(math.log10(scale))) if scale <= 1 else 0.25
        if dtype.value.startswith("i") and raw >= 0:
            score -= 0.02  # the unsigned reading says the same
    if order is not ByteOrder.ABCD:
        score -= 0.02 if order is ByteOrder.CDAB else 0.04  # swapped words are common
    return round(max(score, 0.0), 3)


def _distinct(found: list[Solution]) -> list[Solution]:
    """Settings that read the same registers the same way count once (a u32 whose high
    word is 0 is also a u16; ABCD and BADC of symmetric bytes): the simpler is kept."""
    best: dict[tuple[int, tuple[int, ...], float], Solution] = {}
    for s in sorted(found, key=lambda s: (s.type.words, s.order is not ByteOrder.ABCD,
                                          -s.score)):
        key = (s.address, s.words, round(s.value, 9))
        if key not in best:
            best[key] = s
    return list(best.values())


def _number(x: float) -> str:
    return f"{x:.10g}" if x >= 1 else f"{x:.10f}".rstrip("0")
