"""A profile's ``scale_by`` keys, read and checked against the profile's other fields.

``scale_by: current_ratio`` (or a list: ``[current_ratio, voltage_ratio]``) multiplies
a field's value by other fields of the same device (``model.scaling``). Checked once
the whole field list is known (``extends`` included), each error at the field's own
``scale_by`` line: the factor exists, is a number, is not itself scaled (so there are
no chains and no cycles), is read whenever its field is (not ``poll: never``, no
``interval`` of its own, present in every variant the field is), and the scaled field
is a number nobody writes.
"""

from __future__ import annotations

from collections.abc import Sequence

from rtupoll.config.yamlsrc import Node
from rtupoll.model.codec import DataType
from rtupoll.model.names import close_names
from rtupoll.model.profile import Field, Poll

__all__ = ["check", "names"]


def names(node: Node) -> tuple[str, ...]:
    """``scale_by``: one field name or a list of them."""
    items = node.sequence() if node.is_list else [node]
    if not items:
        raise node.fail("an empty list; name the field(s) the value is multiplied by")
    out = tuple(n.text() for n in items)
    for i, name in enumerate(out):
        if name in out[:i]:
            raise items[i].fail(f"{name!r} is named twice")
    return out


def check(nodes: Sequence[Node], fields: Sequence[Field]) -> None:
    """Each field's ``scale_by`` against the profile's fields; the first error raised at
    that field's ``scale_by``."""
    by_name = {f.name: f for f in fields}
    for node, f in zip(nodes, fields, strict=True):
        if not f.scale_by:
            continue
        at = node.key("scale_by") or node
        why = _not_scalable(f)
        if why:
            raise at.fail(why)
        for name in f.scale_by:
            factor = by_name.get(name)
            if factor is None:
                hint = close_names(name, by_name)
                raise at.fail(f"no field named {name!r}"
                              + (f" (did you mean {hint[0]!r}?)" if hint else ""))
            why = _not_a_factor(f, factor)
            if why:
                raise at.fail(why)


def _numeric(f: Field) -> bool:
    return not (f.enum or f.flags or f.layout.type in (DataType.STRING, DataType.BOOL))


def _not_scalable(f: Field) -> str:
    if not _numeric(f):
        return f"{f.name} is not a number (enum, flags, string or bool): nothing to multiply"
    if f.writable:
        return (f"{f.name} is writable: a write would store the scaled value at the "
                "terminals; a scaled field is read-only")
    return ""


def _not_a_factor(f: Field, factor: Field) -> str:
    """Why ``factor`` cannot scale ``f`` ("" when it can)."""
    name = factor.name
    if factor is f:
        return f"{name} cannot be scaled by itself"
    if not _numeric(factor):
        return f"{name} is not a number (enum, flags, string or bool): it cannot scale {f.name}"
    if factor.scale_by:
        return (f"{name} is itself scaled (by {', '.join(factor.scale_by)}): a factor is "
                "read as stored, so scaled fields cannot scale others (no chains, no loops)")
    if factor.poll is Poll.NEVER:
        return f"{name} is 'poll: never' (reading it has side effects): it cannot scale {f.name}"
    if factor.interval is not None:
        return (f"{name} has an interval of its own; a factor is read in every cycle that "
                f"reads {f.name}, so it takes none")
    if factor.since > f.since:
        return (f"{name} is only in variant {factor.since} and later, {f.name} in "
                f"{f.since} and later: {f.name} would have no factor")
    return ""
