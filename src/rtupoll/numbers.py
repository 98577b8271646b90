"""Numbers as people write them in manuals and on command lines: ``254``, ``0xFE``, ``FEh``."""

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
