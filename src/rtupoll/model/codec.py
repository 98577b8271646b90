"""Registers to values and back: types, byte orders, scale, enums and flags.

Pure functions over tuples of 16-bit words. ``encode`` is the exact inverse of
``decode`` for every value ``decode`` can produce (property-tested), which is what
lets the simulator build its register image from the same profiles the client
decodes with.

Byte orders name where the bytes of the big-endian value ``A B C D`` land on the
wire: ``ABCD`` big-endian, ``BADC`` bytes swapped in each word, ``CDAB`` words
swapped, ``DCBA`` fully little-endian. 64-bit values extend the same rule
(``ABCD`` = words high first, bytes high first).
"""

from __future__ import annotations

import contextlib
import enum
import math
import struct
import sys
from collections.abc import Iterable, Mapping, Sequence

from rtupoll.errors import EncodeError
from rtupoll.frozen import frozen

Value = int | float | str | bool | list[str]


class DataType(str, enum.Enum):
    U16 = "u16"
    I16 = "i16"
    U32 = "u32"
    I32 = "i32"
    U64 = "u64"
    I64 = "i64"
    F32 = "f32"
    F64 = "f64"
    U8 = "u8"  # one byte of a register; Layout.byte says which
    I8 = "i8"
    STRING = "string"
    BOOL = "bool"  # a coil or discrete input

    @property
    def words(self) -> int:
        """Registers a value of this type occupies (strings: given by the field)."""
        return {"u32": 2, "i32": 2, "f32": 2, "u64": 4, "i64": 4, "f64": 4}.get(self.value, 1)

    @property
    def is_integer(self) -> bool:
        return self.value[0] in "ui"

    @property
    def is_float(self) -> bool:
        return self in (DataType.F32, DataType.F64)


F32_MAX = 3.4028234663852886e38  # the largest finite 32-bit float
_STRUCT = {"u16": "H", "i16": "h", "u32": "I", "i32": "i", "u64": "Q", "i64": "q",
           "f32": "f", "f64": "d", "u8": "B", "i8": "b"}


class ByteOrder(str, enum.Enum):
    ABCD = "ABCD"
    BADC = "BADC"
    CDAB = "CDAB"
    DCBA = "DCBA"

    @property
    def swap_bytes(self) -> bool:
        return self in (ByteOrder.BADC, ByteOrder.DCBA)

    @property
    def swap_words(self) -> bool:
        return self in (ByteOrder.CDAB, ByteOrder.DCBA)

    @classmethod
    def from_pair(cls, byteorder: str, wordorder: str) -> ByteOrder:
        """Accept the ``byteorder``/``wordorder`` pair other tools (pymodbus, HA) use."""
        swap_b = {"big": False, "little": True}[byteorder]
        swap_w = {"big": False, "little": True}[wordorder]
        return {(False, False): cls.ABCD, (True, False): cls.BADC,
                (False, True): cls.CDAB, (True, True): cls.DCBA}[(swap_b, swap_w)]


@frozen
class Layout:
    """How one value sits in registers."""

    type: DataType
    words: int = 1
    order: ByteOrder = ByteOrder.ABCD
    scale: float = 1.0
    offset: float = 0.0
    byte: str = "low"  # u8/i8: which byte of the register, "high" or "low"
    shift: int = 0  # bit field: the value's lowest bit in the register (u16/i16)
    width: int = 0  # bit field: how many bits (0: the whole register)

    @property
    def scaled(self) -> bool:
        return self.scale != 1 or self.offset != 0

    @property
    def mask(self) -> int:
        """The register bits this value occupies (a whole register unless a bit field)."""
        if self.width:
            return ((1 << self.width) - 1) << self.shift
        if self.type in (DataType.U8, DataType.I8):
            return 0xFF00 if self.byte == "high" else 0x00FF
        return 0xFFFF


def _to_bytes(words: Sequence[int], order: ByteOrder) -> bytes:
    """Wire words -> the value's bytes in big-endian order."""
    ws = [w & 0xFFFF for w in words]
    if order.swap_words:
        ws.reverse()
    raw = struct.pack(f">{len(ws)}H", *ws)
    if order.swap_bytes:
        raw = b"".join(raw[i + 1 : i + 2] + raw[i : i + 1] for i in range(0, len(raw), 2))
    return raw


def _to_words(raw: bytes, order: ByteOrder) -> tuple[int, ...]:
    """Big-endian value bytes -> wire words (the inverse of ``_to_bytes``)."""
    if order.swap_bytes:
        raw = b"".join(raw[i + 1 : i + 2] + raw[i : i + 1] for i in range(0, len(raw), 2))
    ws = [struct.unpack(">H", raw[i : i + 2])[0] for i in range(0, len(raw), 2)]
    if order.swap_words:
        ws.reverse()
    return tuple(ws)


def decode_raw(words: Sequence[int], layout: Layout) -> int | float | str | bool:
    """The stored value before scale and offset."""
    if len(words) != layout.words:
        raise ValueError(f"{layout.type.value} needs {layout.words} registers, got {len(words)}")
    t = layout.type
    if t is DataType.U16 and not layout.width and not layout.order.swap_bytes:
        return words[0] & 0xFFFF  # the most common register of all, without struct
    if t is DataType.BOOL:
        return bool(words[0])
    if t is DataType.STRING:
        text = _to_bytes(words, ByteOrder.BADC if layout.order.swap_bytes else ByteOrder.ABCD)
        return text.rstrip(b"\x00").decode("latin-1")
    if t in (DataType.U8, DataType.I8):
        byte = (words[0] >> 8) if layout.byte == "high" else words[0]
        return int(struct.unpack(_STRUCT[t.value], bytes([byte & 0xFF]))[0])
    if layout.width:
        bits = (words[0] >> layout.shift) & ((1 << layout.width) - 1)
        if t is DataType.I16 and bits >> (layout.width - 1):
            bits -= 1 << layout.width
        return bits
    value = struct.unpack(">" + _STRUCT[t.value], _to_bytes(words, layout.order))[0]
    return float(value) if t.is_float else int(value)


def short_f32(x: float) -> float:
    """The shortest decimal that is the same 32-bit float: f32 296.15 is stored as
    296.1499938964844, which no one wrote and no one should read. Exact: packing the
    result as f32 gives the same bits back (NaN and infinities pass through)."""
    if not math.isfinite(x):
        return float(x)
    bits = struct.pack(">f", x)
    for digits in range(1, 10):
        candidate = float(f"{x:.{digits}g}")
        with contextlib.suppress(OverflowError):  # rounded up past the largest f32
            if struct.pack(">f", candidate) == bits:
                return candidate
    return float(x)


def decode(words: Sequence[int], layout: Layout) -> int | float | str | bool:
    """Registers -> value, with scale and offset applied (``raw * scale + offset``)."""
    raw = decode_raw(words, layout)
    if not layout.scaled or isinstance(raw, (str, bool)):
        return raw
    if isinstance(raw, int) and float(layout.scale).is_integer() \
            and float(layout.offset).is_integer():
        return raw * int(layout.scale) + int(layout.offset)  # x100 baud stays an integer
    # round away binary noise (3 * 0.1 = 0.30000000000000004) at a precision no
    # 16- or 32-bit register can carry anyway.
    return round(raw * layout.scale + layout.offset, 9)


def encode_raw(raw: int | float | str | bool, layout: Layout,
               current: Sequence[int] | None = None) -> tuple[int, ...]:
    """The stored value -> registers. ``current`` keeps the other byte of a u8 field."""
    t = layout.type
    if t is DataType.BOOL:
        return (1 if raw else 0,)
    if t is DataType.STRING:
        if not isinstance(raw, str):
            raise EncodeError(f"expected text, got {raw!r}")
        data = raw.encode("latin-1", errors="strict") if raw.isascii() else b""
        if raw and not data:
            raise EncodeError(f"{raw!r} is not ASCII text")
        if len(data) > 2 * layout.words:
            raise EncodeError(f"{raw!r} is longer than {2 * layout.words} bytes")
        data = data.ljust(2 * layout.words, b"\x00")
        return _to_words(data, ByteOrder.BADC if layout.order.swap_bytes else ByteOrder.ABCD)
    if isinstance(raw, str):
        raise EncodeError(f"expected a number, got {raw!r}")
    if t.is_float:
        try:
            packed = struct.pack(">" + _STRUCT[t.value], float(raw))
        except OverflowError:  # past the largest f32
            raise EncodeError(f"{raw:g} is outside what {t.value} holds "
                              f"(largest {F32_MAX:.8g})") from None
        return _to_words(packed, layout.order)
    if isinstance(raw, float):
        if not math.isfinite(raw) or raw != int(raw):
            raise EncodeError(f"{raw!r} is not a whole number, as {t.value} needs")
        raw = int(raw)
    lo, hi = bits_range(layout)
    if not lo <= raw <= hi:
        what = f"{layout.width} bits" if layout.width else t.value
        raise EncodeError(f"{raw} is outside {what} ({lo}..{hi})")
    if layout.width:
        other = current[0] if current else 0
        return ((other & ~layout.mask & 0xFFFF) | ((raw << layout.shift) & layout.mask),)
    if t in (DataType.U8, DataType.I8):
        byte = raw & 0xFF
        other = current[0] if current else 0
        word = (other & 0x00FF) | (byte << 8) if layout.byte == "high" else (other & 0xFF00) | byte
        return (word,)
    return _to_words(struct.pack(">" + _STRUCT[t.value], raw), layout.order)


def encode(value: int | float | str | bool, layout: Layout,
           current: Sequence[int] | None = None) -> tuple[int, ...]:
    """Value -> registers: the exact inverse of ``decode``."""
    if layout.scaled and isinstance(value, (int, float)) and not isinstance(value, bool):
        raw: int | float = (value - layout.offset) / layout.scale
        if not math.isfinite(raw):
            raise EncodeError(f"{value:g} is outside what the field holds")
        if layout.type.is_integer:
            nearest = round(raw)
            if abs(nearest - raw) > 1e-6 * max(1.0, abs(raw)):
                step = layout.scale
                raise EncodeError(f"{value} is not a multiple of the field's resolution {step:g}")
            raw = nearest
        return encode_raw(raw, layout, current)
    return encode_raw(value, layout, current)


def stored(words: Sequence[int], layout: Layout) -> int | float | str | bool:
    """The value registers hold, as a reading shows it: an f32 at its own precision
    (``short_f32``), then scale and offset."""
    if layout.type is DataType.F32:
        raw = short_f32(float(decode_raw(words, layout)))
        return round(raw * layout.scale + layout.offset, 9) if layout.scaled else raw
    return decode(words, layout)


def check_exact(value: object, words: Sequence[int], layout: Layout) -> None:
    """The one check of a number against its type, before a write: the registers
    ``words`` (``encode``'s) must read back as ``value`` itself. An f32 holds about 7
    significant digits (99999999 would be 100000000), an f64 about 16, a scaled integer
    only multiples of its scale; ``EncodeError`` (exit 8) names what would be stored."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    back = stored(words, layout)
    if back != value:
        scaled = f" with scale {layout.scale:g}" if layout.scale != 1 else ""
        offset = f" and offset {layout.offset:g}" if layout.offset else ""
        raise EncodeError(f"{_plain(value)} cannot be stored as {layout.type.value}{scaled}"
                          f"{offset}: it would read back as {_plain(back)}")


def _plain(x: object) -> str:
    """A number as typed: the shortest text that is the same float, no ".0"."""
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e16:
        return str(int(x))
    return repr(x) if isinstance(x, float) else str(x)


def bits_range(layout: Layout) -> tuple[int, int]:
    """The stored integers a layout can hold: its type's, or its bit field's."""
    if not layout.width:
        return int_range(layout.type)
    n = layout.width
    return (-(1 << (n - 1)), (1 << (n - 1)) - 1) if layout.type is DataType.I16 \
        else (0, (1 << n) - 1)


def value_range(layout: Layout) -> tuple[float, float]:
    """The values a layout holds at its scale and offset (lowest first): a float type's
    finite range, an integer type's (or bit field's) stored integers scaled."""
    if layout.type.is_float:
        big = F32_MAX if layout.type is DataType.F32 else sys.float_info.max
        return -big, big
    a, b = bits_range(layout)
    lo, hi = sorted((a * layout.scale + layout.offset, b * layout.scale + layout.offset))
    return lo, hi


def int_range(t: DataType) -> tuple[int, int]:
    bits = {"u8": 8, "i8": 8, "u16": 16, "i16": 16, "u32": 32, "i32": 32, "u64": 64, "i64": 64}
    n = bits[t.value]
    return (-(1 << (n - 1)), (1 << (n - 1)) - 1) if t.value[0] == "i" else (0, (1 << n) - 1)


def enum_name(code: int, names: Mapping[int, str]) -> str:
    """An enum code's name; an undocumented code stays visible as ``unknown (N)``."""
    return names.get(code, f"unknown ({code})")


def enum_code(name: str, names: Mapping[int, str]) -> int:
    for code, n in names.items():
        if n == name:
            return code
    raise EncodeError(f"{name!r} is not one of: {', '.join(names.values())}")


def active_flags(raw: int, flags: Mapping[int, str]) -> list[str]:
    """Names of the set bits (flags maps bit masks to names); undocumented bits as ``bit N``."""
    active = [name for mask, name in flags.items() if mask and raw & mask == mask]
    known = 0
    for mask in flags:
        known |= mask
    unknown = raw & ~known
    active += [f"bit {i}" for i in range(unknown.bit_length()) if unknown >> i & 1]
    return active


def flags_mask(names: Iterable[str], flags: Mapping[int, str]) -> int:
    by_name = {n: m for m, n in flags.items()}
    mask = 0
    for name in names:
        if name not in by_name:
            raise EncodeError(f"{name!r} is not one of: {', '.join(by_name)}")
        mask |= by_name[name]
    return mask


def words_to_hex(words: Sequence[int]) -> str:
    return " ".join(f"{w:04X}" for w in words)
