"""``rtupoll guess``: ranking interpretations of registers of a device with no profile."""

from __future__ import annotations

import json
import struct

from cli_runner import rtupoll

from rtupoll.model.guess import interpretations, parse_words


def f32_words(value: float, order: str) -> list[int]:
    """A float as the registers of a device with byte order ``order``."""
    b = struct.pack(">f", value)  # A B C D
    arranged = bytes(b["ABCD".index(c)] for c in order)
    return [arranged[0] << 8 | arranged[1], arranged[2] << 8 | arranged[3]]


def best(words: list[int], first: int = 0, start: int | None = None, count: int | None = None):  # type: ignore[no-untyped-def]
    ranked = interpretations(words, first, first if start is None else start,
                             len(words) if count is None else count)
    return ranked[0]


def test_irnet_concentration_words_are_a_little_endian_float() -> None:
    g = best([0x0000, 0xA0C1], first=6)  # the manual's 00 00 A0 C1 = -20.0
    assert (g.address, g.type, g.order, g.value) == (6, "f32", "DCBA", -20.0)


def test_every_byte_order_of_a_float_is_found() -> None:
    for order in ("ABCD", "BADC", "CDAB", "DCBA"):
        g = best(f32_words(21.5, order))
        assert (g.type, g.order, g.value) == ("f32", order, 21.5), order


def test_small_integers_rank_as_u16() -> None:
    g = best([25, 50, 250, 5000, 0], first=30006)  # the Huiwen example block
    assert g.type == "u16" and g.value in (25, 50, 250, 5000)


def test_a_small_negative_register_is_offered_as_i16() -> None:
    ranked = interpretations([0xFFEC], 0, 0, 1)  # -20
    assert any(g.type == "i16" and g.value == -20 and g.score >= 0.5 for g in ranked)


def test_text_registers_rank_as_a_string() -> None:
    g = best(list(struct.unpack(">4H", b"CO2 ppm\x00")))
    assert g.type == "string" and g.value == "CO2 ppm"


def test_a_float_one_register_off_is_found_and_marked_as_an_offset() -> None:
    words = [0x1234, *f32_words(412.5, "ABCD"), 0x0000]  # asked for 1..2, float at 1 ...
    ranked = interpretations(words, 0, 2, 2)  # ... but the user believed it starts at 2
    hit = next(g for g in ranked if g.type == "f32" and g.value == 412.5)
    assert hit.address == 1 and hit.offset == -1
    assert any("off-by-one" in r for r in hit.reasons)


def test_neighbours_that_read_the_same_way_raise_the_score() -> None:
    alone = best(f32_words(293.15, "DCBA"))
    pair = best(f32_words(293.15, "DCBA") + f32_words(412.5, "DCBA"))
    assert pair.order == "DCBA" and pair.score > alone.score
    assert any("reads well too" in r for r in pair.reasons)


def test_nan_and_absurd_exponents_rank_last() -> None:
    ranked = interpretations([0x7FC0, 0x0000], 0, 0, 2)  # NaN as ABCD
    nan = next(g for g in ranked if g.type == "f32" and g.order == "ABCD")
    assert nan.score == 0.0 and ranked[-1].score <= nan.score + 0.05


def test_parse_words_accepts_hex_words_and_refuses_wider_ones() -> None:
    assert parse_words(["0000", "0xA0C1,1"]) == (0, 0xA0C1, 1)
    result = rtupoll("guess", "--words", "12345")
    assert result.returncode == 2 and "16 bits" in (result.stdout + result.stderr)


def test_cli_offline_words_json_best_first() -> None:
    result = rtupoll("guess", "--words", "0000", "A0C1", "input:6",
                     "--format", "json", "--top", "3")
    assert result.returncode == 0, (result.stdout + result.stderr)
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(rows) == 3
    assert rows[0]["type"] == "f32" and rows[0]["order"] == "DCBA" and rows[0]["value"] == -20.0
    assert rows[0]["table"] == "input" and rows[0]["address"] == 6
    assert rows[0]["score"] >= rows[1]["score"] >= rows[2]["score"]


def test_cli_table_suggests_a_profile_field() -> None:
    result = rtupoll("guess", "--words", "0000", "A0C1", "input:6")
    assert result.returncode == 0
    assert "{name: value_0006, table: input, address: 0x0006, type: f32, order: DCBA}" \
        in (result.stdout + result.stderr)


def test_cli_needs_port_and_address_without_words() -> None:
    result = rtupoll("guess", "input:6")
    assert result.returncode == 2 and "--port and --address" in (result.stdout + result.stderr)
