"""The codec: golden vectors from the seed manuals and exact round trips."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rtupoll.model.codec import (
    ByteOrder,
    DataType,
    EncodeError,
    Layout,
    active_flags,
    decode,
    decode_raw,
    encode,
    enum_name,
    flags_mask,
    int_range,
)

F32 = DataType.F32


@pytest.mark.parametrize(
    ("words", "order", "value"),
    [
        # IRNET-PRO: wire bytes 00 00 A0 C1 are -20.0 (fully little-endian)
        ((0x0000, 0xA0C1), ByteOrder.DCBA, -20.0),
        # IRNET-PRO: wire bytes 00 00 48 42 are 50.0
        ((0x0000, 0x4842), ByteOrder.DCBA, 50.0),
        # the same -20.0 (0xC1A00000) in the other three orders
        ((0xC1A0, 0x0000), ByteOrder.ABCD, -20.0),
        ((0xA0C1, 0x0000), ByteOrder.BADC, -20.0),
        ((0x0000, 0xC1A0), ByteOrder.CDAB, -20.0),
    ],
)
def test_f32_golden_vectors(words: tuple[int, int], order: ByteOrder, value: float) -> None:
    layout = Layout(F32, 2, order)
    assert decode(words, layout) == value
    assert encode(value, layout) == words


@pytest.mark.parametrize(
    ("order", "words"),
    [
        (ByteOrder.ABCD, (0x0102, 0x0304)),
        (ByteOrder.BADC, (0x0201, 0x0403)),
        (ByteOrder.CDAB, (0x0304, 0x0102)),
        (ByteOrder.DCBA, (0x0403, 0x0201)),
    ],
)
def test_u32_byte_orders_place_bytes_as_named(order: ByteOrder, words: tuple[int, int]) -> None:
    assert decode(words, Layout(DataType.U32, 2, order)) == 0x01020304


def test_u64_word_order_extends_to_four_words() -> None:
    value = 0x0102030405060708
    assert encode(value, Layout(DataType.U64, 4, ByteOrder.ABCD)) == (0x0102, 0x0304, 0x0506,
                                                                      0x0708)
    assert encode(value, Layout(DataType.U64, 4, ByteOrder.DCBA)) == (0x0807, 0x0605, 0x0403,
                                                                      0x0201)


def test_byteorder_wordorder_pairs_name_the_four_orders() -> None:
    assert ByteOrder.from_pair("big", "big") is ByteOrder.ABCD
    assert ByteOrder.from_pair("little", "big") is ByteOrder.BADC
    assert ByteOrder.from_pair("big", "little") is ByteOrder.CDAB
    assert ByteOrder.from_pair("little", "little") is ByteOrder.DCBA


def test_signed_16_bit_co2_and_temperature() -> None:
    assert decode((0x0190,), Layout(DataType.I16)) == 400  # CO2Meter AN117 example
    assert decode((0xFFE2,), Layout(DataType.I16)) == -30


def test_scale_gives_manual_units_and_inverts() -> None:
    tvoc = Layout(DataType.U16, scale=0.001)  # Huiwen: ppm x 1000
    assert decode((0x0032,), tvoc) == 0.05
    assert decode((0x00FA,), tvoc) == 0.25
    assert encode(0.25, tvoc) == (0x00FA,)
    with pytest.raises(EncodeError, match="resolution"):
        encode(0.0005, tvoc)


def test_integral_scale_keeps_integers() -> None:
    baud = decode((192,), Layout(DataType.U16, scale=100))  # radar: baud rate / 100
    assert baud == 19200 and isinstance(baud, int)
    assert encode(19200, Layout(DataType.U16, scale=100)) == (192,)


def test_offset_and_scale_together() -> None:
    layout = Layout(DataType.I16, scale=0.1, offset=-40)
    assert decode((650,), layout) == 25.0
    assert encode(25.0, layout) == (650,)


def test_u8_fields_share_one_register() -> None:
    low = Layout(DataType.U8, byte="low")
    high = Layout(DataType.U8, byte="high")
    word = 0x0A07  # Banner 30030: error code 10 in the high byte, DIP switches 7 in the low
    assert decode((word,), low) == 7
    assert decode((word,), high) == 10
    # a read-modify-write keeps the other byte
    assert encode(42, low, current=(word,)) == (0x0A2A,)
    assert encode(3, high, current=(word,)) == (0x0307,)


def test_strings_keep_character_order_and_strip_padding() -> None:
    layout = Layout(DataType.STRING, 4)
    words = encode("CO2", layout)
    assert words == (0x434F, 0x3200, 0x0000, 0x0000)
    assert decode(words, layout) == "CO2"
    swapped = Layout(DataType.STRING, 2, ByteOrder.BADC)
    assert encode("ppm", swapped) == (0x7070, 0x006D)
    with pytest.raises(EncodeError, match="longer than 4 bytes"):
        encode("ppm %vol", swapped)


def test_out_of_range_values_are_refused() -> None:
    with pytest.raises(EncodeError, match=r"outside u16 \(0..65535\)"):
        encode(70000, Layout(DataType.U16))
    with pytest.raises(EncodeError, match="whole number"):
        encode(1.5, Layout(DataType.U16))
    with pytest.raises(EncodeError, match="expected a number"):
        encode("ten", Layout(DataType.U16))


def test_wrong_register_count_is_an_error() -> None:
    with pytest.raises(ValueError, match="needs 2 registers, got 1"):
        decode_raw((1,), Layout(F32, 2))


def test_enums_keep_unknown_codes_visible() -> None:
    names = {0: "NO_ERROR", 2: "E2PROM_CKSM_ERROR"}
    assert enum_name(2, names) == "E2PROM_CKSM_ERROR"
    assert enum_name(7, names) == "unknown (7)"


def test_flags_list_active_names_and_undocumented_bits() -> None:
    flags = {0x01: "WARMUP", 0x10: "INVALID_READINGS"}
    assert active_flags(0x00, flags) == []
    assert active_flags(0x11, flags) == ["WARMUP", "INVALID_READINGS"]
    assert active_flags(0x0101, flags) == ["WARMUP", "bit 8"]
    assert flags_mask(["WARMUP", "INVALID_READINGS"], flags) == 0x11


# --- exact inverse, property-tested -------------------------------------------------

INT_TYPES = [DataType.U16, DataType.I16, DataType.U32, DataType.I32, DataType.U64, DataType.I64]
ORDERS = list(ByteOrder)


@given(st.sampled_from(INT_TYPES), st.sampled_from(ORDERS), st.data())
def test_integers_round_trip(t: DataType, order: ByteOrder, data: st.DataObject) -> None:
    layout = Layout(t, t.words, order)
    lo, hi = int_range(t)
    value = data.draw(st.integers(lo, hi))
    words = encode(value, layout)
    assert len(words) == t.words and all(0 <= w <= 0xFFFF for w in words)
    assert decode(words, layout) == value


@given(st.sampled_from([DataType.F32, DataType.F64]), st.sampled_from(ORDERS), st.data())
def test_any_register_image_decodes_and_encodes_back(t: DataType, order: ByteOrder,
                                                     data: st.DataObject) -> None:
    """encode(decode(words)) == words for every register image (NaNs aside)."""
    layout = Layout(t, t.words, order)
    words = tuple(data.draw(st.lists(st.integers(0, 0xFFFF), min_size=t.words,
                                     max_size=t.words)))
    value = decode(words, layout)
    assert isinstance(value, float)
    if not math.isnan(value):
        assert encode(value, layout) == words


@given(st.floats(width=32, allow_nan=False), st.sampled_from(ORDERS))
def test_f32_values_round_trip(value: float, order: ByteOrder) -> None:
    layout = Layout(F32, 2, order)
    assert decode(encode(value, layout), layout) == value


@given(st.sampled_from([DataType.U16, DataType.I16, DataType.U32, DataType.I32]),
       st.sampled_from([0.1, 0.01, 0.001, 0.5, 10.0, 100.0]),
       st.sampled_from([0.0, -40.0, 273.15]), st.data())
def test_scaled_integers_round_trip(t: DataType, scale: float, offset: float,
                                    data: st.DataObject) -> None:
    layout = Layout(t, t.words, ByteOrder.ABCD, scale, offset)
    lo, hi = int_range(t)
    words = encode(data.draw(st.integers(lo, hi)), Layout(t, t.words))
    assert encode(decode(words, layout), layout) == words


@given(st.text(alphabet=st.characters(min_codepoint=0x21, max_codepoint=0x7E), max_size=8),
       st.sampled_from([ByteOrder.ABCD, ByteOrder.BADC]))
def test_strings_round_trip(text: str, order: ByteOrder) -> None:
    layout = Layout(DataType.STRING, 4, order)
    assert decode(encode(text, layout), layout) == text


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.sampled_from(["low", "high"]))
def test_u8_write_changes_only_its_byte(word: int, value: int, byte: str) -> None:
    layout = Layout(DataType.U8, byte=byte)
    (new,) = encode(value, layout, current=(word,))
    assert decode((new,), layout) == value
    keep = 0xFF00 if byte == "low" else 0x00FF
    assert new & keep == word & keep


def test_f32_struct_agrees_with_ieee754() -> None:
    (bits,) = struct.unpack(">I", struct.pack(">f", -20.0))
    assert bits == 0xC1A00000
