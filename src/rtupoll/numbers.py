"""Numbers in people's words: read as manuals and command lines write them (``254``,
``0xFE``, ``FEh``), and a count written with its noun (``1 device``, ``3 devices``)."""

from __future__ import annotations


def parse_int(text: str) -> int:
    """Decimal, 0x hex or a trailing h (``254``, ``0xFE``, ``FEh``), as manuals write them."""
    t = text.strip().lower()
    if t.endswith("h") and len(t) > 1:
        return int(t[:-1], 16)
    return int(t, 0)


def parse_unit(text: str) -> int:
    """A unit (slave) address 0..255; ValueError says what is wrong, in a user's words."""
    try:
        unit = parse_int(text)
    except ValueError:
        raise ValueError(f"{text!r} is not an address (0-255, decimal or 0x..)") from None
    if not 0 <= unit <= 255:
        raise ValueError(f"address {unit} is outside 0..255")
    return unit


def count(n: int, noun: str, plural: str = "") -> str:
    """``n`` and its noun, singular for exactly one: "1 device", "0 devices", "3 devices"
    (``plural`` where adding "s" is not the plural)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
