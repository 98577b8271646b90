"""Numbers as manuals write them, and unit addresses (rtupoll.numbers)."""

from __future__ import annotations

import pytest

from rtupoll.numbers import parse_int, parse_unit


@pytest.mark.parametrize(("text", "value"), [("254", 254), ("0xFE", 254), ("FEh", 254),
                                             ("0x7536", 30006), (" 12 ", 12)])
def test_numbers_as_manuals_write_them(text: str, value: int) -> None:
    assert parse_int(text) == value


@pytest.mark.parametrize(("text", "message"), [
    ("abc", "'abc' is not an address (0-255, decimal or 0x..)"),
    ("256", "address 256 is outside 0..255"),
    ("-1", "address -1 is outside 0..255"),
])
def test_bad_unit_addresses_say_why(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_unit(text)
