"""Registers of a device with no profile -> interpretations ranked by plausibility.

Pure. The usual way to learn a new device is to read a few registers and try every
type and byte order by hand until a number looks right. This does the trying and
ranks what it finds, so a new profile starts from evidence:

- each position from one below to one past the asked-for range (manuals count
  registers from 0 or from 1, and half the forum threads are an off-by-one);
- u16, i16, u32, i32, f32, f64 in every byte order (ABCD, BADC, CDAB, DCBA) and
  ASCII text in both byte orders;
- scored by what real devices hold: floats with sane exponents and few significant
  digits, small integers, printable text, and the same reading making sense for
  the neighbouring value too (one register map rarely mixes byte orders).

Scores are relative, between 0 and 1; they rank, they do not prove.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.model.codec import ByteOrder, DataType, Layout, decode_raw

ORDERS = tuple(ByteOrder)
NUMERIC = (DataType.U32, DataType.I32, DataType.F32, DataType.F64)


@frozen
class Guess:
    """One way to read the registers starting at ``address``."""

    address: int  # wire address of the first register
    type: str  # u16, i16, u32, i32, f32, f64, string
    order: str  # ABCD/BADC/CDAB/DCBA ("" for 16-bit values; strings AB or BA)
    words: tuple[int, ...]
    value: int | float | str
    score: float
    reasons: tuple[str, ...]
    offset: int = 0  # registers before (-) or past the asked-for range (+); 0 inside

    @property
    def text(self) -> str:
        if isinstance(self.value, float):
            return f"{self.value:.7g}" if self.type == "f32" else f"{self.value:.12g}"
        if isinstance(self.value, str):
            return repr(self.value)
        return str(self.value)


def _float_score(v: float, single: bool) -> tuple[float, str]:
    if math.isnan(v) or math.isinf(v):
        return 0.0, "not a number"
    if v == 0:
        return 0.2, "zero: every type reads all-zero registers as 0"
    mag = abs(v)
    if mag < 1e-6 or mag > 1e9:
        return 0.05, f"exponent {math.floor(math.log10(mag))}: no sensor reports that"
    digits = 7 if single else 12
    text = f"{v:.{digits}g}".lstrip("-").replace(".", "").lstrip("0").rstrip("0")
    if 1e-3 <= mag <= 1e6:
        # Few digits are only a small bonus: a live sensor's value has a noisy mantissa,
        # while a misaligned read that pairs a value's high half with a zero register
        # looks temptingly round.
        if len(text) <= 4:
            return 0.75, "a float with a sane exponent and few significant digits"
        if len(text) < digits - 1:
            return 0.72, "a float with a sane exponent and a clean mantissa"
        return 0.7, "a float with a sane exponent"
    return 0.3, "a float, very small or very large"


def _int_score(v: int, signed: bool, wide: bool) -> tuple[float, str]:
    if v == 0:
        return 0.25, "zero: says little"
    mag = abs(v)
    if signed and v < 0:
        return (0.5, "a small negative number") if mag < 1000 else (0.15, "a large negative")
    if mag < 10_000:
        return (0.5 if wide else 0.55), "a small whole number"
    if mag < 1_000_000 and wide:
        return 0.4, "a moderate whole number"
    if not wide and v == 0xFFFF:
        return 0.1, "all ones: often 'no value' or -1"
    return 0.15, "a large whole number"


def _text_score(raw: bytes) -> tuple[float, str, str]:
    text = raw.rstrip(b"\x00 ")
    if len(text) < 2:
        return 0.0, "", "no text"
    printable = sum(32 <= b < 127 for b in text)
    alnum = sum(chr(b).isalnum() for b in text)
    decoded = text.decode("latin-1")
    if printable == len(text) and alnum >= 2:
        return 0.8, decoded, "printable ASCII text"
    return 0.3 * printable / len(text), decoded, "partly printable"


def _value(words: Sequence[int], dtype: DataType, order: ByteOrder) -> int | float:
    v = decode_raw(words, Layout(dtype, dtype.words, order))
    assert isinstance(v, (int, float)) and not isinstance(v, bool)
    return v


def _score(dtype: DataType, value: int | float) -> tuple[float, str]:
    if dtype.is_float:
        return _float_score(float(value), dtype is DataType.F32)
    return _int_score(int(value), dtype.value.startswith("i"), dtype.words > 1)


def interpretations(words: Sequence[int], first: int, start: int, count: int
                    ) -> list[Guess]:
    """Every reading of ``words`` (read from wire address ``first``), best first.

    ``start``/``count`` is the range the user asked about; values starting one
    register outside it are included, marked with their offset and a small penalty.
    """
    ws = tuple(w & 0xFFFF for w in words)
    lo, hi = max(first, start - 1), min(first + len(ws), start + count + 1)
    out: list[Guess] = []
    for p in range(lo, hi):
        out += _at(ws, p - first, p, start, start + count)
    out = _neighbours(out)
    out = _merge(out)
    return sorted(out, key=lambda g: (-g.score, abs(g.offset), len(g.words), g.address))


def _at(ws: tuple[int, ...], i: int, address: int, lo: int, hi: int) -> list[Guess]:
    """Every reading of the values starting at ``ws[i]`` (wire ``address``); asked: lo..hi."""
    found: list[Guess] = []

    def add(dtype: str, order: str, n: int, value: int | float | str, score: float,
            why: str) -> None:
        offset = address - lo if address < lo else max(0, address + n - hi)
        where: tuple[str, ...] = ()
        if offset:
            side = "before" if offset < 0 else "past"
            where = (f"{abs(offset)} register(s) {side} the range asked for: an off-by-one "
                     "in the manual?",)
            score -= 0.1
        elif n > 1 and dtype != "string" and hi - lo >= n and (address - lo) % n:
            where = (f"not aligned with the range asked for (starts {address - lo} in)",)
            score -= 0.1
        found.append(Guess(address, dtype, order, ws[i : i + n], value,
                           round(max(0.0, score), 3), (why, *where), offset))

    w = ws[i]
    score, why = _int_score(w, False, False)
    add("u16", "", 1, w, score, why)
    if w & 0x8000:
        signed = w - 0x10000
        score, why = _int_score(signed, True, False)
        add("i16", "", 1, signed, score, why)
    for dtype in NUMERIC:
        n = dtype.words
        if i + n > len(ws):
            continue
        for order in ORDERS:
            v = _value(ws[i : i + n], dtype, order)
            if dtype is DataType.I32 and v >= 0:
                continue  # the same as u32
            score, why = _score(dtype, v)
            if not dtype.is_float and n > 1 and 0 in ws[i : i + n] and any(ws[i : i + n]):
                score -= 0.1
                why += "; one register is 0: also two u16"
            add(dtype.value, order.value, n, v, score, why)
    n = len(ws) - i  # text runs to the end of what was read
    raw = b"".join(struct.pack(">H", x) for x in ws[i:])
    for swap, data in (("AB", raw), ("BA", _swap(raw))):
        score, text, why = _text_score(data)
        if n >= 2 and score >= 0.5:
            add("string", swap, n, text, score + 0.02 * min(len(text), 6), why)
    return found


def _swap(raw: bytes) -> bytes:
    return b"".join(raw[k + 1 : k + 2] + raw[k : k + 1] for k in range(0, len(raw), 2))


def _neighbours(guesses: list[Guess]) -> list[Guess]:
    """Reward a reading whose neighbour (the next or previous value) reads well the same way."""
    by_key = {(g.address, g.type, g.order): g for g in guesses}
    out = []
    for g in guesses:
        n = len(g.words)
        if g.type in ("u16", "i16", "string") or g.score < 0.5:
            out.append(g)
            continue
        near = [by_key.get((g.address + d, g.type, g.order)) for d in (n, -n)]
        good = [x for x in near if x is not None and x.score >= 0.5]
        if good:
            where = "next" if good[0].address > g.address else "previous"
            g = Guess(g.address, g.type, g.order, g.words, g.value,
                      round(min(1.0, g.score + 0.08), 3),
                      (*g.reasons, f"the {where} {g.type} {g.order} reads well too "
                       f"({good[0].text})"), g.offset)
        out.append(g)
    return out


def _merge(guesses: list[Guess]) -> list[Guess]:
    """Byte orders that give the same value (symmetric bytes) become one row: 'ABCD=BADC'."""
    seen: dict[tuple[int, str, int | float | str], int] = {}
    out: list[Guess] = []
    for g in guesses:
        key = (g.address, g.type, g.value)
        if key in seen and g.order:
            k = seen[key]
            first = out[k]
            out[k] = Guess(first.address, first.type, f"{first.order}={g.order}", first.words,
                           first.value, max(first.score, g.score), first.reasons, first.offset)
            continue
        seen[key] = len(out)
        out.append(g)
    return out


def parse_words(tokens: Sequence[str]) -> tuple[int, ...]:
    """``0000 A0C1`` or ``0x0000,0xA0C1``: 16-bit words in hex, as a manual or sniffer shows."""
    words = []
    for token in (t for part in tokens for t in part.replace(",", " ").split()):
        digits = token[2:] if token.lower().startswith("0x") else token
        try:
            value = int(digits, 16)
        except ValueError:
            raise UsageError(f"{token!r} is not a 16-bit word in hex (e.g. 0000 A0C1)") from None
        if not 0 <= value <= 0xFFFF or len(digits) > 4:
            raise UsageError(f"{token!r} does not fit 16 bits (four hex digits)")
        words.append(value)
    return tuple(words)
