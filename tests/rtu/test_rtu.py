"""RTU primitives: numbers as manuals write them, unit addresses, timing."""

from __future__ import annotations

import pytest

from rtupoll.numbers import parse_int, parse_unit
from rtupoll.rtu import Framing, transaction_wire_time


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


def test_inter_frame_silence() -> None:
    assert Framing(9600).silence == pytest.approx(3.5 * 10 / 9600)
    assert Framing(115200).silence == 0.00175  # fixed above 19200 baud
    assert Framing(9600, parity="E").bits_per_char == 11


def test_transaction_wire_time_at_9600() -> None:
    # 8-byte request, 9-byte reply, two silences: 17.7 ms + 7.3 ms
    assert transaction_wire_time(Framing(9600), 8, 9) == pytest.approx(0.02500, abs=1e-4)
