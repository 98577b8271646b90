"""A field's ``decode:`` key (a documented encoding, ``model.transforms``), read and checked.

``decode: four_quadrant_pf`` names how the number the registers hold is unfolded into
the value. Each error is raised at the field's ``decode`` line: an encoding rtupoll does
not know (the known ones listed), a field that is not a plain number (enum, flags,
string, bool), a writable field (a decoded field is read-only), a ``range`` outside the
values the encoding can give; a ``typical`` outside them at the ``typical`` line. A
field without a ``range`` gets the encoding's span as its range (the simulator keeps
its values there).
"""

from __future__ import annotations

from collections.abc import Mapping

from rtupoll.config.yamlsrc import Node
from rtupoll.model.codec import DataType
from rtupoll.model.transforms import Transform

__all__ = ["read"]

_NAMES = [t.value for t in Transform]


def read(m: Mapping[str, Node], dtype: DataType, coded: bool, access: str,
         lo: float | None, hi: float | None
         ) -> tuple[Transform | None, float | None, float | None]:
    """(the field's encoding, its range) from its keys ``m``; ``coded``: it has an enum
    or flags. Without ``decode``: (None, ``lo``, ``hi``) unchanged."""
    node = m.get("decode")
    if node is None:
        return None, lo, hi
    transform = node.choice(Transform, _NAMES)
    if coded or dtype in (DataType.STRING, DataType.BOOL):
        raise node.fail(f"{transform.value} decodes a number, and this field is not one "
                        "(enum, flags, string or bool)")
    if "W" in access:
        raise node.fail("a decoded field is read-only (a write would store the value "
                        "without its encoding)")
    slo, shi = transform.span
    if lo is None or hi is None:
        lo, hi = slo, shi
    elif lo < slo or hi > shi:
        raise node.fail(f"range [{lo:g}, {hi:g}] is outside what {transform.value} gives "
                        f"({slo:g}..{shi:g})")
    typical = m.get("typical")
    if typical is not None:
        value = typical.number()
        if not slo <= value <= shi:
            raise typical.fail(f"typical {value:g} is outside what {transform.value} gives "
                            f"({slo:g}..{shi:g})")
    return transform, lo, hi
