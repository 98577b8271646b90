"""Reading and validating one profile file: YAML -> ``profile.Profile``.

``read_profile`` rejects anything wrong with ``file:line: path: message``; it also says
which files it read (the profile and each profile it ``extends``), with the bytes it
parsed, so ``compiled`` can tell later whether the result still holds. Only
``library.load_profile`` calls it, when the compiled profile cache has no answer.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import yaml

from rtupoll.config import scale_by, transform_key
from rtupoll.config.compiled import Source
from rtupoll.config.idle_gap import idle_gap
from rtupoll.config.paths import find_parent
from rtupoll.config.yamlsrc import Node, from_bytes, read_bytes
from rtupoll.errors import EncodeError
from rtupoll.model.codec import ByteOrder, DataType, Layout, bits_range, encode
from rtupoll.model.profile import (
    MAX_LABEL,
    AddressChange,
    Addresses,
    Addressing,
    Check,
    Choice,
    Document,
    Field,
    Limits,
    Poll,
    Profile,
    Provenance,
    Serial,
    Severity,
    Variant,
    Verification,
    is_modicon_reference,
    squashed,
)
from rtupoll.numbers import parse_int
from rtupoll.rtu import Table
from rtupoll.rtu.functions import MAX_REGISTERS

T = TypeVar("T")
V = TypeVar("V", float, str)  # a value a field holds
MAX_FIELDS = 4096  # fields in one profile (the largest bundled: 40)

_TYPES = [t.value for t in DataType]
_ORDERS = [o.value for o in ByteOrder]
_TOP_KEYS = {"id", "vendor", "model", "manual", "notes", "serial", "addressing", "addresses",
             "limits", "byte_order", "byteorder", "wordorder", "fields", "identify",
             "set_address", "variant", "kind", "extends", "without",
             "provenance", "identification", "server_id"}
_FIELD_KEYS = {"name", "table", "address", "type", "length", "order", "byteorder", "wordorder",
               "byte", "scale", "offset", "unit", "description", "access", "enum", "flags",
               "range", "values", "poll", "alone", "since", "source", "sentinels", "precision",
               "interval", "counter", "typical", "scale_by", "decode", "label"}


def read_profile(path: Path) -> tuple[Profile, list[Source]]:
    """Read and validate one profile file (and the profiles it ``extends``); with it, the
    files read, this one first, then its parent, the parent's parent ..."""
    sources: list[Source] = []
    root, top, field_nodes = _merged(path, (), sources)
    missing = sorted({"id", "vendor", "model", "manual", "addressing"} - top.keys())
    if missing:
        raise root.fail(f"missing required key {missing[0]!r}")
    if not field_nodes and "fields" not in top:
        raise root.fail("missing required key 'fields'")
    addressing = top["addressing"].choice(Addressing, [a.value for a in Addressing])
    serial = _serial(top["serial"]) if "serial" in top else Serial(baudrates=(9600,))
    limits = _limits(top["limits"]) if "limits" in top else Limits()
    default_order = _order(top, top.get("byte_order"), ByteOrder.ABCD)
    pid = top["id"].text()
    if not pid.replace("-", "").isalnum() or pid != pid.lower():
        raise top["id"].fail("ids are lower-case letters, digits and dashes")

    fields: list[Field] = []
    for fnode in field_nodes:
        fields.append(_field(fnode, addressing, default_order, limits))
    # bit fields share registers with each other; they are checked here, the rest below
    plain = [i for i, f in enumerate(fields) if not f.layout.width]
    anchor = top.get("fields") or root
    _check_fields(_Fields(anchor, [field_nodes[i] for i in plain]), [fields[i] for i in plain])
    _check_shared(field_nodes, fields)
    scale_by.check(field_nodes, fields)
    warnings = _check_titles(field_nodes, fields)
    by_name = {f.name: f for f in fields}

    profile = Profile(
        id=pid,
        vendor=top["vendor"].text(),
        model=top["model"].text(),
        manual=top["manual"].text(),
        notes=top["notes"].text() if "notes" in top else "",
        kind=top["kind"].text() if "kind" in top else "",
        extends=_extends(root),
        addressing=addressing,
        serial=serial,
        limits=limits,
        addresses=_addresses(top["addresses"]) if "addresses" in top else Addresses(),
        byte_order=default_order,
        fields=tuple(fields),
        identify=tuple(_check(n, by_name) for n in top["identify"].sequence())
        if "identify" in top else (),
        set_address=_address_change(top["set_address"], by_name, limits)
        if "set_address" in top else AddressChange(unsupported="the profile does not say"),
        variant=_variant(top["variant"], by_name) if "variant" in top else None,
        provenance=_provenance(top["provenance"]) if "provenance" in top else Provenance(),
        path=str(path),
        identification=_identification(top["identification"])
        if "identification" in top else (),
        server_id=_hex_bytes(top["server_id"]) if "server_id" in top else b"",
        warnings=warnings,
    )
    if path.stem != pid:
        raise top["id"].fail(f"id {pid!r} must match the file name {path.name!r}")
    return profile, sources


def _extends(root: Node) -> str:
    raw = root.node
    for k, v in raw.value if isinstance(raw, yaml.MappingNode) else ():
        if str(k.value) == "extends" and isinstance(v, yaml.ScalarNode):
            return str(v.value)
    return ""


class _Fields(Node):
    """A field list assembled from several files (``extends``): each field keeps its own
    file and line, so an error in an inherited field points at the parent profile."""

    def __init__(self, anchor: Node, items: list[Node]) -> None:
        super().__init__(anchor.node, anchor.file, anchor.path, anchor._error)
        self._items = items

    def sequence(self) -> list[Node]:
        return list(self._items)


def _merged(path: Path, seen: tuple[Path, ...], sources: list[Source]
            ) -> tuple[Node, dict[str, Node], list[Node]]:
    """The root node, top-level keys and field nodes of a profile, its ``extends`` chain
    resolved; each file read is added to ``sources``.

    The child's keys replace the parent's; its fields are added to the parent's, a
    field of the same name replaces the parent's in place, and ``without`` drops some.
    """
    data = read_bytes(path)
    root = from_bytes(data, str(path))
    top = root.mapping(_TOP_KEYS)
    own = top["fields"].sequence() if "fields" in top else []
    if "extends" not in top:
        if "without" in top:
            raise top["without"].fail("only a profile that 'extends' another drops fields")
        sources.append(Source(path, data, ""))
        return root, top, own
    parent_id = top["extends"].text()
    sources.append(Source(path, data, parent_id))
    parent_path = find_parent(parent_id, path)
    if parent_path is None:
        raise top["extends"].fail(f"no profile {parent_id!r} next to this file or on the "
                                  f"profile search path")
    if parent_path.resolve() in seen or parent_path.resolve() == path.resolve():
        raise top["extends"].fail(f"{parent_id!r} extends this profile: a loop")
    _, base, inherited = _merged(parent_path, (*seen, path.resolve()), sources)
    drop: dict[str, Node] = {}
    for n in top["without"].sequence() if "without" in top else []:
        drop[n.text()] = n
    known = {_field_name(n) for n in inherited}
    for name, n in drop.items():
        if name not in known:
            raise n.fail(f"{parent_id} has no field {name!r} to drop")
    mine = {_field_name(n): n for n in own}
    fields = [mine.pop(_field_name(n), n) for n in inherited if _field_name(n) not in drop]
    fields += [n for n in own if _field_name(n) in mine]
    merged = {k: v for k, v in base.items() if k != "fields"}
    merged.update((k, v) for k, v in top.items() if k not in ("extends", "without"))
    return root, merged, fields


def _field_name(node: Node) -> str:
    """A field's name, read without resolving the node (which ``mapping`` does once)."""
    raw: yaml.Node | None = node.node
    while isinstance(raw, yaml.MappingNode):
        merged = None
        for k, v in raw.value:
            if k.tag == "tag:yaml.org,2002:merge":
                merged = v
            elif str(k.value) == "name" and isinstance(v, yaml.ScalarNode):
                return str(v.value)
        raw = merged
    return f"#{node.line}"



def _check_shared(nodes: list[Node], fields: list[Field]) -> None:
    """Bit fields (and u8 halves) in a register: their bits must not overlap anything."""
    by_register: dict[tuple[Table, int], list[int]] = {}
    for i, f in enumerate(fields):
        for r in range(f.address, f.end):
            by_register.setdefault((f.table, r), []).append(i)
    first: dict[str, Field] = {}
    for i, f in enumerate(fields):
        seen = first.setdefault(f.name, f)
        if seen is not f and (f.layout.width or seen.layout.width):
            raise nodes[i].fail(f"duplicate field name {f.name!r} (first at line {seen.line})")
        if not f.layout.width:
            continue
        for j in by_register[f.table, f.address]:
            g = fields[j]
            if j != i and not f.can_share(g):
                raise nodes[i].fail(
                    f"{f.name} overlaps {g.name} (line {g.line}) in the {f.table.value} table")


def _opt(m: Mapping[str, Node], key: str, get: Callable[[Node], T], default: T) -> T:
    return get(m[key]) if key in m else default


def _order(m: Mapping[str, Node], node: Node | None, default: ByteOrder) -> ByteOrder:
    if node is not None:
        return node.choice(ByteOrder, _ORDERS)
    if "byteorder" in m or "wordorder" in m:
        pair = []
        for key in ("byteorder", "wordorder"):
            n = m.get(key)
            pair.append(n.choice(_identity, ["big", "little"]) if n else "big")
            if n and pair[-1] not in ("big", "little"):
                raise n.fail(f"{pair[-1]!r} is not one of: big, little")
        return ByteOrder.from_pair(pair[0], pair[1])
    return default


def _serial(node: Node) -> Serial:
    m = node.mapping({"baudrate", "parity", "bytesize", "stopbits", "baudrates", "deassert_dtr"})
    baud = m["baudrate"].integer(300, 4_000_000) if "baudrate" in m else 9600
    rates: tuple[int, ...] = _opt(
        m, "baudrates", lambda n: tuple(r.integer(300, 4_000_000) for r in n.sequence()), (baud,))
    if baud not in rates:
        raise m["baudrate"].fail(f"{baud} is not among baudrates {list(rates)}")
    parity = m["parity"].text().upper() if "parity" in m else "N"
    if parity not in ("N", "E", "O"):
        raise m["parity"].fail(f"{parity!r} is not one of: N, E, O")
    return Serial(
        baudrate=baud, parity=parity,
        bytesize=m["bytesize"].integer(7, 8) if "bytesize" in m else 8,
        stopbits=m["stopbits"].integer(1, 2) if "stopbits" in m else 1,
        baudrates=rates,
        deassert_dtr=m["deassert_dtr"].flag() if "deassert_dtr" in m else False,
    )


def _limits(node: Node) -> Limits:
    m = node.mapping({"max_registers", "max_gap", "functions", "timeout", "retries",
                      "turnaround", "silent_on_error", "lost_after_powerup", "idle_gap"})
    d = Limits()
    timeout = m["timeout"].number() if "timeout" in m else d.timeout
    if not 0.01 <= timeout <= 30:
        raise m["timeout"].fail(f"{timeout} s is outside 0.01..30 s")
    return Limits(
        max_registers=_opt(m, "max_registers", lambda n: n.integer(1, MAX_REGISTERS),
                           d.max_registers),
        max_gap=_opt(m, "max_gap", lambda n: n.integer(0, MAX_REGISTERS - 1), d.max_gap),
        functions=_opt(m, "functions",
                       lambda n: frozenset(f.integer(1, 127) for f in n.sequence()), d.functions),
        timeout=timeout,
        retries=_opt(m, "retries", lambda n: n.integer(0, 10), d.retries),
        turnaround=_opt(m, "turnaround", Node.number, d.turnaround),
        silent_on_error=_opt(m, "silent_on_error", Node.flag, False),
        lost_after_powerup=_opt(m, "lost_after_powerup", lambda n: n.integer(0, 100), 0),
        idle_gap=_opt(m, "idle_gap", idle_gap, 0.0),
    )


def _addresses(node: Node) -> Addresses:
    m = node.mapping({"range", "default", "reserved", "any"})
    lo, hi = 1, 247
    if "range" in m:
        seq = m["range"].sequence()
        if len(seq) != 2:
            raise m["range"].fail("expected [lowest, highest]")
        lo, hi = seq[0].integer(1, 255), seq[1].integer(1, 255)
        if lo > hi:
            raise m["range"].fail(f"lowest {lo} is above highest {hi}")
    reserved: dict[int, str] = _opt(
        m, "reserved", lambda n: {k.integer(0, 255): v.text() for k, v in n.items()}, {})
    any_ = _opt(m, "any", lambda n: n.integer(1, 255), None)
    default = _opt(m, "default", lambda n: n.integer(1, 255), lo)
    if not (lo <= default <= hi or default == any_):
        raise m["default"].fail(f"{default} is outside the range {lo}..{hi}")
    return Addresses(lo=lo, hi=hi, default=default, reserved=reserved, any=any_)


def _choice(v: Node) -> Choice:
    if not v.is_mapping:
        return Choice(v.text())
    cm = v.mapping({"name", "severity", "description"}, {"name"})
    return Choice(
        cm["name"].text(),
        _opt(cm, "severity", lambda n: n.choice(Severity, [s.value for s in Severity]),
             Severity.OK),
        _opt(cm, "description", Node.text, ""),
    )


def _choices(node: Node, what: str, fit: int) -> tuple[dict[int, Choice], Choice | None]:
    """An enum or flags map; ``other`` (enums only) names every undocumented code."""
    out: dict[int, Choice] = {}
    other = None
    for k, v in node.items():
        if k.value() == "other" and what == "code":
            other = _choice(v)
            continue
        code = k.integer()
        if not 0 <= code <= fit:
            raise k.fail(f"{what} {code} does not fit the field (0..{fit})")
        if what == "bit mask" and code == 0:
            raise k.fail("bit mask 0 never shows; a flag needs at least one bit")
        out[code] = _choice(v)
    names = [c.name for c in out.values()] + ([other.name] if other else [])
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise node.fail(f"{what} name {sorted(dup)[0]!r} is used twice")
    return out, other


def _field(node: Node, addressing: Addressing, default_order: ByteOrder, limits: Limits) -> Field:
    """One entry of ``fields``: where it is, how it is stored, what its values mean and
    who may write it, each checked by its own helper below."""
    m = node.mapping(_FIELD_KEYS, {"name", "table", "address", "type"})
    name = m["name"].text()
    if not name.isidentifier() or name != name.lower():
        raise m["name"].fail(f"{name!r} is not a lower_snake_case name")
    if name.startswith("_") or name == "last_seen":  # rtupoll's own keys in MQTT state
        raise m["name"].fail(f"{name!r} is reserved (a name may not start with '_', and "
                             "last_seen is the time of the last reading)")
    table = m["table"].choice(Table, [t.value for t in Table])
    dtype = m["type"].choice(DataType, _TYPES)
    written, shift, width = _address(m["address"], dtype, table)
    wire = _wire_address(m["address"], addressing, table, written)
    layout = _layout(node, m, dtype, table, default_order, limits, shift, width)
    enum_map, other, flags = _meanings(m, layout)
    lo, hi = _value_range(m, layout)
    access = _access(m, table, width)
    transform, lo, hi = transform_key.read(m, dtype, bool(enum_map or flags), access, lo, hi)
    source = m["source"].text() if "source" in m else "manual"
    if source not in ("manual", "public"):
        raise m["source"].fail(f"{source!r} is not one of: manual, public")
    counter = m["counter"].flag() if "counter" in m else False
    if counter and (enum_map or flags or dtype in (DataType.STRING, DataType.BOOL)):
        raise m["counter"].fail("only a number can be a counter")
    return Field(
        name=name, table=table, address=wire, layout=layout,
        written=addressing.show(table, wire) + _bits_text(shift, width),
        unit=m["unit"].text() if "unit" in m else "",
        description=m["description"].text() if "description" in m else "",
        access=access, enum=enum_map, other=other, flags=flags, minimum=lo, maximum=hi,
        values=tuple(_fitting(n, n.number(), layout) for n in
                     (m["values"].sequence() if "values" in m else [])),
        poll=m["poll"].choice(Poll, [p.value for p in Poll]) if "poll" in m else Poll.DEFAULT,
        alone=m["alone"].flag() if "alone" in m else False,
        since=m["since"].integer(0, 255) if "since" in m else 0,
        source=source, sentinels=_sentinels(m["sentinels"], layout) if "sentinels" in m else {},
        precision=m["precision"].integer(-6, 9) if "precision" in m else None,
        interval=_opt(m, "interval", _interval, None), counter=counter,
        typical=_typical(m["typical"], layout) if "typical" in m else None, line=node.line,
        scale_by=scale_by.names(m["scale_by"]) if "scale_by" in m else (), transform=transform,
        label=_label(m["label"]) if "label" in m else "",
    )


def _label(node: Node) -> str:
    """``label``: the field's short name for people, one line of at most MAX_LABEL
    characters (what else a label must be is checked with the other fields')."""
    text = node.text()
    if not text.strip():
        raise node.fail("an empty label")
    if text != text.strip() or any(c in text for c in "\n\r\t"):
        raise node.fail(f"{text!r}: a label is one line, with no spaces at its ends")
    if len(text) > MAX_LABEL:
        raise node.fail(f"{len(text)} characters; a label has at most {MAX_LABEL}")
    return text


def _check_titles(nodes: list[Node], fields: list[Field]) -> tuple[str, ...]:
    """Each field's title (``Field.title``: its label, else from its description) must say
    what it measures and tell it from the profile's other fields: not only a unit (any
    unit of the profile's fields), at most MAX_LABEL characters, and none equal to
    another's (case and spaces aside). A ``label:`` that breaks this is an error; a title
    from a description, a warning (returned, one per field, for ``profiles check``)."""
    units = {squashed(f.unit) for f in fields if f.unit}
    first: dict[str, int] = {}
    problems: dict[int, str] = {}
    for i, f in enumerate(fields):
        key = squashed(f.title)
        j = first.setdefault(key, i)
        if j != i:
            g = fields[j]
            if g.label and not f.label:  # the label is the one to blame
                i, f, j, g = j, g, i, f
            where = f"line {g.line}" if nodes[j].file == nodes[i].file else \
                f"{Path(nodes[j].file).name}:{g.line}"
            problems.setdefault(i, f"the title of {g.name} ({where}) too")
        if key in units:
            problems.setdefault(i, "only a unit")
        elif len(f.title) > MAX_LABEL:
            problems.setdefault(i, f"{len(f.title)} characters (at most {MAX_LABEL})")
    warnings: list[str] = []
    for i, problem in sorted(problems.items()):
        f, node = fields[i], nodes[i]
        given = node.key("label") if f.label else None
        if given is not None:
            raise given.fail(f"{f.title!r} is {problem}: a label says what the field "
                             "measures, and tells it from the profile's other fields")
        at = node.key("description") or node.key("name") or node
        warnings.append(str(at.fail(f"warning: {f.name} is titled {f.title!r}, {problem}; "
                                    "give it a 'label:'")))
    return tuple(warnings)


def _wire_address(node: Node, addressing: Addressing, table: Table, written: int) -> int:
    """The address on the wire of an address as the profile writes it."""
    if addressing in (Addressing.DIRECT, Addressing.MODICON) and table.is_register:
        base = table.modicon_base
        if not (base < written <= base + 9999 if addressing is Addressing.DIRECT
                else is_modicon_reference(table, written)):
            raise node.fail(f"{written} is not a {table.value} register reference "
                            f"({base + 1}..{base + 9999}"
                            + (")" if addressing is Addressing.DIRECT
                               else f", or {base * 10 + 1}..{base * 10 + 65536})"))
    wire = addressing.to_wire(table, written)
    if not 0 <= wire <= 0xFFFF:
        raise node.fail(f"wire address {wire} is outside 0..65535")
    return wire


def _layout(node: Node, m: Mapping[str, Node], dtype: DataType, table: Table,
            default_order: ByteOrder, limits: Limits, shift: int, width: int) -> Layout:
    """How the value is stored: registers, byte and word order, scale and offset."""
    if dtype is DataType.STRING:
        if "length" not in m:
            raise node.fail("a string needs 'length' (bytes)")
        words = (m["length"].integer(1, 250) + 1) // 2
    else:
        if "length" in m:
            raise m["length"].fail("only strings have a length")
        words = dtype.words
    if (dtype is DataType.BOOL) != (table in (Table.COIL, Table.DISCRETE)):
        raise m["type"].fail(f"{dtype.value} does not fit a {table.value} field")
    byte = m["byte"].choice(_identity, ["high", "low"]) if "byte" in m else "low"
    if byte not in ("high", "low"):
        raise m["byte"].fail(f"{byte!r} is not one of: high, low")
    if "byte" in m and dtype not in (DataType.U8, DataType.I8):
        raise m["byte"].fail("only u8/i8 fields sit in one byte")
    # The profile's byte_order is for values wider than one register; a 16-bit value is
    # a standard big-endian Modbus register unless the field names its own order.
    order = _order(m, m.get("order"), default_order if words > 1 else ByteOrder.ABCD)
    scale = m["scale"].number() if "scale" in m else 1.0
    if scale == 0:
        raise m["scale"].fail("scale cannot be 0")
    if words > limits.max_registers:
        raise m["type"].fail(
            f"{words} registers are more than the device reads at once ({limits.max_registers})")
    return Layout(dtype, words, order, scale, m["offset"].number() if "offset" in m else 0.0,
                  byte, shift, width)


def _meanings(m: Mapping[str, Node], layout: Layout
              ) -> tuple[dict[int, Choice], Choice | None, dict[int, Choice]]:
    """``enum`` (codes and the catch-all) or ``flags`` (bit masks): (enum, other, flags)."""
    if "enum" not in m and "flags" not in m:
        return {}, None, {}
    dtype = layout.type
    if not dtype.is_integer:
        raise (m.get("enum") or m["flags"]).fail(f"enum and flags need an integer type, "
                                                 f"not {dtype.value}")
    if "enum" in m and "flags" in m:
        raise m["flags"].fail("a field has enum or flags, not both")
    fit = (1 << (layout.width or (8 if dtype in (DataType.U8, DataType.I8)
                                  else 16 * layout.words))) - 1
    if "enum" in m:
        enum_map, other = _choices(m["enum"], "code", fit)
        return enum_map, other, {}
    return {}, None, _choices(m["flags"], "bit mask", fit)[0]


def _value_range(m: Mapping[str, Node], layout: Layout) -> tuple[float | None, float | None]:
    """``range``: [lowest, highest] a write may set, within what the type can hold."""
    if "range" not in m:
        return None, None
    seq = m["range"].sequence()
    if len(seq) != 2:
        raise m["range"].fail("expected [lowest, highest]")
    lo, hi = seq[0].number(), seq[1].number()
    if lo > hi:
        raise m["range"].fail(f"lowest {lo:g} is above highest {hi:g}")
    if layout.type.is_integer:
        tlo, thi = bits_range(layout)
        vlo, vhi = sorted((tlo * layout.scale + layout.offset, thi * layout.scale + layout.offset))
        if lo < vlo - 1e-9 or hi > vhi + 1e-9:
            raise m["range"].fail(f"[{lo:g}, {hi:g}] does not fit {layout.type.value} "
                                  f"with this scale and offset ({vlo:g}..{vhi:g})")
    return lo, hi


def _access(m: Mapping[str, Node], table: Table, width: int) -> str:
    access = m["access"].text().upper() if "access" in m else "R"
    if access not in ("R", "RW", "W"):
        raise m["access"].fail(f"{access!r} is not one of: R, RW, W")
    if "W" in access and table in (Table.INPUT, Table.DISCRETE):
        raise m["access"].fail(f"{table.value} registers cannot be written")
    if "W" in access and width:
        raise m["access"].fail("bit fields are read-only (a write would need read-modify-"
                               "write of the register, which 'rtupoll write' does for u8 only)")
    return access


def _fitting(node: Node, value: V, layout: Layout) -> V:
    """A value the profile gives for the field (``values``, ``typical``): it must fit."""
    try:
        encode(value, layout)
    except EncodeError as exc:
        raise node.fail(f"{node.value()} does not fit the field: {exc}") from None
    return value


def _typical(node: Node, layout: Layout) -> float | str:
    """A field's everyday value (the simulator starts there): it must fit the field."""
    if layout.type is DataType.STRING:
        return _fitting(node, node.text(), layout)
    return _fitting(node, node.number(), layout)


_MAX_WRITTEN = 465536  # the highest address a profile may write: the 6-digit 4xxxxx form


def _address(node: Node, dtype: DataType, table: Table) -> tuple[int, int, int]:
    """``address``: a register, or ``REGISTER:SHIFT:WIDTH`` for a bit field inside one
    (read as written: YAML would take an unquoted 12288:4:4 for a base-60 number)."""
    text = node.text() if not node.is_mapping and not node.is_list else ""
    if ":" not in text:
        return node.integer(0, _MAX_WRITTEN), 0, 0
    parts = text.split(":")
    try:
        reg, shift, width = (int(p.strip(), 0) for p in parts)
    except ValueError:
        raise node.fail(f"{text!r} is not REGISTER:SHIFT:WIDTH (e.g. 0x3200:4:4)") from None
    if dtype not in (DataType.U16, DataType.I16) or not table.is_register:
        raise node.fail(f"a bit field is u16 or i16 in a register, not {dtype.value}")
    if not 0 <= reg <= _MAX_WRITTEN:
        raise node.fail(f"{reg} is outside 0..{_MAX_WRITTEN}")
    if not 0 <= shift <= 15 or not 1 <= width <= 16 - shift:
        raise node.fail(f"bits {shift}..{shift + width - 1} are not inside one 16-bit register")
    return reg, shift, width


def _bits_text(shift: int, width: int) -> str:
    if not width:
        return ""
    return f" bit {shift}" if width == 1 else f" bits {shift}-{shift + width - 1}"


def _interval(node: Node) -> float:
    if node.value() == "once":  # read at start, then never again (an import's scan_interval 0)
        return math.inf
    seconds = node.number()
    if not 0.05 <= seconds <= 86400:
        raise node.fail(f"{seconds:g} s is outside 0.05..86400 s")
    return seconds


def _sentinels(node: Node, layout: Layout) -> dict[int | float, Choice]:
    """Stored values (before scale) that mean "no reading", each with a name."""
    if layout.type in (DataType.STRING, DataType.BOOL):
        raise node.fail(f"a {layout.type.value} field has no sentinel values")
    out: dict[int | float, Choice] = {}
    for k, v in node.items():
        if layout.type.is_integer:
            code = k.integer()
            lo, hi = bits_range(layout)
            # written as the register shows it (0xFFFF) or as the signed value (-1)
            if code > hi and layout.type.value[0] == "i" and code <= 2 * hi + 1:
                code -= 2 * (hi + 1)
            if not lo <= code <= hi:
                raise k.fail(f"sentinel {code} does not fit the field ({lo}..{hi})")
            key: int | float = code
        else:
            key = k.number()
        choice = _choice(v)
        if not v.is_mapping:  # a bare name: it is not a reading, so not "ok"
            choice = Choice(choice.name, Severity.WARNING)
        out[key] = choice
    return out


def _check_fields(node: Node, fields: list[Field]) -> None:
    items = node.sequence()
    seen: dict[str, int] = {}
    for i, f in enumerate(fields):
        if f.name in seen:
            raise items[i].mapping()["name"].fail(
                f"duplicate field name {f.name!r} (first at line {seen[f.name]})")
        seen[f.name] = f.line
    if len(fields) > MAX_FIELDS:
        raise node.fail(f"{len(fields)} fields; a profile holds at most {MAX_FIELDS}")
    # n log n: in address order, a field is compared only with the fields still open at its
    # start; those all share that register, so (allowed: two u8 halves) there are at most 2
    order = sorted(range(len(fields)), key=lambda k: (fields[k].table.value, fields[k].address))
    open_: list[int] = []
    for k in order:
        f = fields[k]
        open_ = [j for j in open_ if fields[j].table is f.table and fields[j].end > f.address]
        for j in open_:
            g = fields[j]
            if not f.can_share(g):  # two u8 halves may (bit fields are checked apart)
                i, first = (k, g) if j < k else (j, f)  # reported at the later one in the file
                later = fields[i]
                raise items[i].mapping()["address"].fail(
                    f"{later.name} overlaps {first.name} (line {first.line}) in the "
                    f"{later.table.value} table")
        open_.append(k)


def _check(node: Node, by_name: Mapping[str, Field]) -> Check:
    m = node.mapping({"field", "range", "equals", "equals_address", "exception"}, {"field"})
    name = m["field"].text()
    if name not in by_name:
        raise m["field"].fail(f"no field named {name!r}")
    rng = None
    if "range" in m:
        seq = m["range"].sequence()
        if len(seq) != 2:
            raise m["range"].fail("expected [lowest, highest]")
        rng = (seq[0].number(), seq[1].number())
    equals: tuple[str | int | float, ...] = ()
    if "equals" in m:
        vals = m["equals"].sequence() if m["equals"].is_list else [m["equals"]]
        equals = tuple(v.value() for v in vals)
    return Check(name, rng, m["equals_address"].flag() if "equals_address" in m else False,
                 equals, m["exception"].integer(1, 255) if "exception" in m else None)


def _address_change(node: Node, by_name: Mapping[str, Field], limits: Limits) -> AddressChange:
    m = node.mapping({"field", "function", "reply", "unsupported"})
    if "unsupported" in m:
        if len(m) > 1:
            raise node.fail("'unsupported' stands alone")
        return AddressChange(unsupported=m["unsupported"].text())
    if "field" not in m:
        raise node.fail("needs 'field' (the address register) or 'unsupported' (why not)")
    name = m["field"].text()
    f = by_name.get(name)
    if f is None:
        raise m["field"].fail(f"no field named {name!r}")
    if f.table is not Table.HOLDING or f.words != 1:
        raise m["field"].fail(f"{name} must be a one-register holding field")
    function = m["function"].integer() if "function" in m else 6
    if function not in (6, 16):
        raise m["function"].fail(f"{function} is not 6 or 16")
    if function not in limits.functions:
        raise m["function"].fail(f"the device does not support function {function} "
                                 f"(limits.functions)")
    reply = m["reply"].text() if "reply" in m else "echo"
    if reply not in ("echo", "none", "malformed", "any"):
        raise m["reply"].fail(f"{reply!r} is not one of: echo, none, malformed, any")
    return AddressChange(field=name, function=function, reply=reply)


def _variant(node: Node, by_name: Mapping[str, Field]) -> Variant:
    m = node.mapping({"field", "name", "on_exception"}, {"field", "name"})
    name = m["field"].text()
    if name not in by_name:
        raise m["field"].fail(f"no field named {name!r}")
    on_exc = {k.integer(1, 255): v.integer(0, 255) for k, v in m["on_exception"].items()} \
        if "on_exception" in m else {}
    return Variant(name, m["name"].text(), on_exc)



def _identification(node: Node) -> tuple[tuple[int, str], ...]:
    """``identification``: the objects read device identification answers, by the
    standard's name (``vendor_name`` ...) or a private id (``0x80``..``0xFF``)."""
    from rtupoll.rtu.identification import OBJECT_KEYS

    out = {}
    for key, value in node.items():
        name = key.text()
        if name in OBJECT_KEYS:
            obj = OBJECT_KEYS[name]
        else:
            try:
                obj = parse_int(name)
            except ValueError:
                obj = -1
            if not 0x80 <= obj <= 0xFF:
                raise key.fail(f"not an identification object: {name!r} (one of "
                               f"{', '.join(OBJECT_KEYS)}, or a private id 0x80..0xFF)")
        text = value.text()
        if not text.isascii() or not 0 < len(text) <= 240:
            raise value.fail("an identification object is 1..240 ASCII characters")
        out[obj] = text
    missing = [k for k, o in OBJECT_KEYS.items() if o <= 2 and o not in out]
    if missing:
        raise node.fail(f"missing {missing[0]!r}: a device that identifies itself has the "
                        "three basic objects (vendor_name, product_code, "
                        "major_minor_revision)")
    return tuple(sorted(out.items()))


def _hex_bytes(node: Node) -> bytes:
    try:
        data = bytes.fromhex(node.text())
    except ValueError:
        raise node.fail("expected bytes in hex, e.g. '0A' or '01 02'") from None
    if not 1 <= len(data) <= 240:
        raise node.fail("1..240 bytes")
    return data


def _identity(text: str) -> str:
    return text


def _provenance(node: Node) -> Provenance:
    """``provenance``: the documents the profile was written from and how far it is
    verified; a verified profile names at least one document."""
    m = node.mapping({"level", "sources", "notes"}, {"level"})
    level = m["level"].choice(Verification, [v.value for v in Verification])
    docs: list[Document] = []
    for n in m["sources"].sequence() if "sources" in m else []:
        d = n.mapping({"title", "version", "where"}, {"title", "where"})
        for key in ("title", "where"):
            if not d[key].text().strip():
                raise d[key].fail(f"an empty {key}")
        docs.append(Document(d["title"].text(), d["where"].text(),
                             d["version"].text() if "version" in d else ""))
    if level is not Verification.UNVERIFIED and not docs:
        raise (m.get("sources") or m["level"]).fail(
            f"a profile verified by {level.value!r} names its sources (title, where)")
    if level is Verification.TWO and len(docs) < 2:
        raise m["sources"].fail(f"'{level.value}' names two sources, not {len(docs)}")
    return Provenance(level, tuple(docs), m["notes"].text() if "notes" in m else "", True)
