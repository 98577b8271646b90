"""An ``idle_gap:`` key, one rule wherever it is written: a profile's ``limits`` and a
site file's device or bus (seconds, ``model.profile.idle_gap_error``'s range)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rtupoll.model.profile import idle_gap_error

if TYPE_CHECKING:
    from rtupoll.config.yamlsrc import Node


def idle_gap(node: Node) -> float:
    """An ``idle_gap:`` in seconds (a profile's ``limits``; a site file's device or bus)."""
    gap = node.number()
    why = idle_gap_error(gap)
    if why:
        raise node.fail(why)
    return float(gap)
