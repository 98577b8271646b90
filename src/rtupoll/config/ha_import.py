"""Home Assistant ``modbus:`` YAML -> rtupoll profiles and a site file.

Home Assistant describes Modbus devices as hubs (a serial port or a gateway) with
sensors, each naming its slave, register, type and scaling. rtupoll keeps the device
knowledge (a profile) apart from where the device sits (a site file), so each
(hub, slave) pair becomes one profile and one site entry.

What converts: ``sensors`` and register/coil ``binary_sensors`` (``slave`` or
``device_address``, ``address``, ``input_type``, ``data_type``, ``count``, ``swap``,
``scale``, ``offset``, ``precision``, ``unit_of_measurement``, ``scan_interval`` (0: read
once), ``state_class: total_increasing``, ``nan_value``, ``slave_count``/``virtual_count``),
the hub's ``timeout`` and ``retries``, and the same in the form before Home Assistant
2021.6 (``sensor: - platform: modbus`` with ``registers:``). ``!include``, the
``!include_dir_*`` tags, ``!secret`` and ``!env_var`` are followed (``ha_yaml``). Every
other setting, and what cannot convert (``custom`` structures, Modbus TCP hubs, switches
and other writable entities, sensors that overlap another's registers, clamping options),
is reported, one line each, as ``file:line: path: not converted/carried over: why``; the
rest still converts. Names keep their distinction in ASCII (``ascii_name``) and their
original spelling as the field's description.
Pure: reads one file, returns text; the CLI writes the files.
"""

from __future__ import annotations

import math
import re
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rtupoll.config.ha_yaml import HaYaml
from rtupoll.config.yamlsrc import Node
from rtupoll.errors import ConfigError
from rtupoll.model.codec import DataType
from rtupoll.rtu.functions import MAX_REGISTERS

_TYPES = {"int16": "i16", "uint16": "u16", "int32": "i32", "uint32": "u32", "int64": "i64",
          "uint64": "u64", "float32": "f32", "float64": "f64", "string": "string",
          "int8": "i8", "uint8": "u8"}
_LEGACY = {("int", 1): "i16", ("int", 2): "i32", ("int", 4): "i64", ("uint", 1): "u16",
           ("uint", 2): "u32", ("uint", 4): "u64", ("float", 2): "f32", ("float", 4): "f64"}
_SWAP = {"none": "ABCD", "byte": "BADC", "word": "CDAB", "word_byte": "DCBA"}
_PLATFORMS = ("sensors", "binary_sensors")
_UNSUPPORTED = ("switches", "climates", "covers", "lights", "fans")
DEFAULT_SCAN = 15.0  # Home Assistant's default scan_interval, seconds
ONCE = math.inf  # a field read once at start (``interval: once`` in the profile)
IDLE = 60  # a site device whose every field is read once: how often the poller looks


@dataclass
class Device:
    """One (hub, slave) pair: its future profile's fields and where it sits."""

    hub: str
    slave: int
    fields: list[dict[str, Any]] = field(default_factory=list)
    intervals: list[float] = field(default_factory=list)

    prefix: str = "ha"

    @property
    def id(self) -> str:
        return f"{self.prefix}-{slug(self.hub, '-')}-{self.slave}"


@dataclass
class Hub:
    name: str
    port: str
    serial: dict[str, Any]
    devices: dict[int, Device] = field(default_factory=dict)
    device_settings: dict[str, Any] = field(default_factory=dict)  # timeout_ceiling, retries
    entry: Any = None  # the source's hub mapping (an ``Entry``), for its leftover keys


@dataclass
class Imported:
    """The result: profile texts by id, the site file text, and what was not converted."""

    profiles: dict[str, str]
    site: str
    report: list[str]
    converted: int


def import_ha(path: Path) -> Imported:
    """Convert a Home Assistant configuration (a file with ``modbus:``, or the list of
    hubs itself; ``!include``, ``!secret`` and the rest followed as Home Assistant does)
    into profiles and a site file."""
    tree = HaYaml(path)
    root = tree.root
    report: list[str] = []
    top = tree.mapping(root) if root.is_mapping else {}
    if root.is_mapping and "modbus" not in top:
        raise root.fail("no 'modbus:' section")
    hubs_node = top["modbus"] if root.is_mapping else root
    items = tree.sequence(hubs_node) if tree.is_list(hubs_node) else [tree.resolve(hubs_node)]
    hubs: list[Hub] = []
    converted = 0
    for hnode in items:
        hub = _hub(tree, hnode, report)
        if hub is None:
            continue
        hubs.append(hub)
        m = hub.entry
        for key in _UNSUPPORTED:
            if m.has(key):
                report.append(_at(m.node_of(key), f"not converted: {key} (rtupoll polls; "
                                                  f"writes are 'rtupoll write' commands, "
                                                  f"not entities)"))
        for platform in _PLATFORMS:
            for snode in tree.sequence(m.node_of(platform)) if m.has(platform) else []:
                converted += _sensor(hub, Entry(tree, snode), platform, report)
        m.report_rest(report, _HUB_NOTES)
    converted += _legacy_platforms(tree, top, hubs, report)
    profiles = {}
    for hub in hubs:
        for dev in hub.devices.values():
            if dev.fields:
                profiles[dev.id] = profile_text(dev, hub, path)
    report.sort(key=file_order)
    return Imported(profiles, site_text(hubs, path), report, converted)


def file_order(note: str) -> tuple[str, int]:
    """Notes in file order: by file, then line (``FILE:LINE: ...``)."""
    m = re.match(r"(.*?):(\d+): ", note)
    return (m[1], int(m[2])) if m else (note, 0)


class Entry:
    """One mapping of the source: its keys, and which of them were carried over, so that
    every key nobody used is listed (nothing is dropped silently)."""

    def __init__(self, tree: HaYaml, node: Node) -> None:
        self.tree, self.node = tree, node
        self.m = tree.mapping(node)
        self.used: set[str] = set()

    def has(self, key: str) -> bool:
        return key in self.m

    def node_of(self, key: str) -> Node:
        """The key's node (marked as carried over), or the mapping's own for a note."""
        if key in self.m:
            self.used.add(key)
            return self.m[key]
        return self.node

    def text(self, key: str, default: str = "") -> str:
        return self.tree.text(self.node_of(key)) if key in self.m else default

    def report_rest(self, report: list[str], why: dict[str, str], name: str = "") -> None:
        for key, node in self.m.items():
            if key not in self.used:
                reason = why.get(key, "rtupoll has no such setting")
                who = f"{name!r}: " if name else ""
                shown = key if _NAME.fullmatch(key) else "a key that is no setting's name"
                report.append(_at(node, f"not carried over: {who}{shown} ({reason})"))


# why a hub or sensor setting has no rtupoll counterpart (anything else: a generic note)
_HUB_NOTES = {
    "delay": "a pause after connecting: rtupoll keeps the 3.5-character silence before "
             "every frame and needs no extra start-up pause",
    "message_wait_milliseconds": "an extra pause between requests: rtupoll keeps the "
                                 "3.5-character silence and learns each device's timing; "
                                 "a device that needs more gets limits.turnaround in its "
                                 "profile",
    "close_comm_on_error": "rtupoll keeps the port open and drains the line after an error",
    "retry_on_empty": "rtupoll retries every unanswered request (retries)",
}
_SENSOR_NOTES = {
    "unique_id": "Home Assistant's entity id; rtupoll's MQTT discovery makes its own ids",
    "icon": "a Home Assistant display setting",
    "structure": "goes with data_type custom",
}


_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_ -]{0,63}")  # a setting's or a hub's key


def _shown(path: str) -> str:
    """A node's dotted path as a message shows it: a key that is no plain name (a
    line of some other file, a value put where a key goes) as ``?``, never echoed."""
    parts = []
    for part in path.split("."):
        key, sep, index = part.partition("[")
        parts.append((key if not key or _NAME.fullmatch(key) else "?") + sep + index)
    return ".".join(parts)


def _at(node: Node, message: str) -> str:
    path = _shown(node.path)
    return f"{node.file}:{node.line}: {path + ': ' if path else ''}{message}"


def _hub(tree: HaYaml, node: Node, report: list[str]) -> Hub | None:
    m = Entry(tree, node)
    name = m.text("name", "modbus_hub")
    kind = m.text("type", "serial")
    if kind == "serial":
        if m.text("method", "rtu") != "rtu":
            report.append(_at(m.node_of("method"), "not converted: hub uses Modbus ASCII; "
                                                   "rtupoll speaks RTU"))
            return None
        serial = {"baudrate": int(m.text("baudrate", "9600")),
                  "parity": m.text("parity", "N").upper(),
                  "bytesize": int(m.text("bytesize", "8")),
                  "stopbits": int(m.text("stopbits", "1"))}
        hub = Hub(name, m.text("port", "/dev/ttyUSB0"), serial)
    elif kind == "rtuovertcp":
        hub = Hub(name, f"tcp://{m.text('host')}:{m.text('port', '502')}",
                  {"baudrate": 9600, "parity": "N", "bytesize": 8, "stopbits": 1})
    else:
        report.append(_at(m.node_of("type"), f"not converted: hub {name!r} is type {kind} "
                                             f"(Modbus TCP/UDP); rtupoll speaks RTU, over a "
                                             f"serial port or an RTU-over-TCP gateway"))
        return None
    hub.entry = m
    if m.has("timeout"):  # Home Assistant's wait for each reply: rtupoll's longest wait
        hub.device_settings["timeout_ceiling"] = _seconds(m.text("timeout"))
    if m.has("retries"):
        hub.device_settings["retries"] = int(m.text("retries"))
    return hub


def _sensor(hub: Hub, m: Entry, platform: str, report: list[str],
            default_interval: float = DEFAULT_SCAN) -> int:
    """Add one HA sensor's field(s) to its device; returns how many fields it became."""
    name = m.text("name", f"sensor_{m.node.line}")

    def skip(key: str, why: str) -> int:
        report.append(_at(m.node_of(key), f"not converted: {name!r}: {why}"))
        return 0

    if not m.has("address"):
        return skip("address", "no address")
    slave = int(m.text("slave", m.text("device_address", "0")), 0)
    if not 1 <= slave <= 247:
        report.append(_at(m.node_of("slave" if m.has("slave") else "device_address"),
                          f"{name!r}: slave {slave} is not a device address (Home "
                          f"Assistant's default 0 is broadcast); taken as 1"))
        slave = 1
    address = int(m.text("address"), 0)
    table = m.text("input_type", "holding" if platform == "sensors" else "coil")
    if table not in ("holding", "input", "coil", "discrete_input", "discrete"):
        return skip("input_type", f"input_type {table}")
    table = "discrete" if table.startswith("discrete") else table
    f: dict[str, Any] = {"name": "", "table": table, "address": address}
    words = 1
    if platform == "binary_sensors":
        if table in ("coil", "discrete"):
            f["type"] = "bool"
        else:  # Home Assistant tests bit 0 of the register
            f.update(type="u16", address=f"{address}:0:1")
    else:
        if table in ("coil", "discrete"):
            return skip("input_type", f"a sensor on {table}s (use a binary_sensor)")
        dtype = m.text("data_type", "int16")
        count = int(m.text("count", "1"))
        t = _TYPES.get(dtype) or _LEGACY.get((dtype, count))
        if t is None:
            why = ("data_type custom (a struct format) has no rtupoll equivalent"
                   if dtype == "custom" else f"data_type {dtype} (count {count})")
            m.node_of("structure")
            return skip("data_type", why)
        if t in ("i8", "u8"):
            return skip("data_type", f"{dtype}: Home Assistant's 8-bit types read a whole "
                                     f"register; rtupoll needs to know which byte")
        f["type"] = t
        wide = DataType(t).words > 1  # a number over several registers (not a string)
        words = count if t == "string" else DataType(t).words
        if t == "string":
            f["length"] = 2 * count
        swap = m.text("swap", "none")
        if swap not in _SWAP:
            return skip("swap", f"swap {swap}")
        if swap in ("word", "word_byte") and not wide:
            return skip("swap", f"swap {swap} on a one-register {dtype}")
        if swap != "none":
            f["order"] = _SWAP[swap]
        elif wide:
            f["order"] = "ABCD"
        for key in ("scale", "offset"):
            if m.has(key):
                value = float(m.text(key))
                if (key == "scale" and value != 1) or (key == "offset" and value):
                    f[key] = int(value) if value.is_integer() else value
        if m.has("precision"):
            f["precision"] = int(m.text("precision"))
        if m.has("unit_of_measurement"):
            f["unit"] = m.text("unit_of_measurement")
        if m.text("state_class") in ("total_increasing", "total"):
            f["counter"] = True
        if m.has("nan_value"):
            f["sentinels"] = {int(m.text("nan_value"), 0): "NOT_AVAILABLE"}
    label = name + (f" ({m.text('device_class')})" if m.has("device_class") else "")
    if label != slug(name, "_"):
        f["description"] = label
    for key in ("min_value", "max_value", "zero_suppress"):
        if m.has(key):
            report.append(_at(m.node_of(key), f"{name!r}: {key} (Home Assistant clamps or "
                                              f"zeroes values) is not converted; the raw "
                                              f"value is reported"))
    if m.has("lazy_error_count"):
        report.append(_at(m.node_of("lazy_error_count"), f"{name!r}: lazy_error_count "
                                                         f"ignored (rtupoll reports every "
                                                         f"failed read)"))
    if table in ("holding", "input") and 30001 <= address <= 49999:
        report.append(_at(m.node_of("address"), f"{name!r}: address {address} looks like a "
                                                f"3xxxx/4xxxx reference; Home Assistant "
                                                f"sends it as written (wire 0x{address:04X}), "
                                                f"and so does this profile. If the manual "
                                                f"means register {address % 10000}, use "
                                                f"{address % 10000 - 1}"))
    interval = _seconds(m.text("scan_interval", str(default_interval)))
    if interval == 0:  # Home Assistant: read once at start, then only when asked
        interval = ONCE
        report.append(_at(m.node_of("scan_interval"), f"{name!r}: scan_interval 0: read "
                                                      f"once at start and not polled again "
                                                      f"(interval: once), as in Home "
                                                      f"Assistant"))
    more = int(m.text("slave_count", m.text("virtual_count", "0")))
    m.node_of("name")
    m.node_of("state_class")
    m.report_rest(report, _SENSOR_NOTES, name)
    return _add(hub, slave, f, words, interval, name, m.node_of("address"), report, more)


def _add(hub: Hub, slave: int, f: dict[str, Any], words: int, interval: float, name: str,
         at: Node, report: list[str], more: int = 0) -> int:
    """Add a field (and ``more`` copies at the following registers) to a device."""
    dev = hub.devices.setdefault(slave, Device(hub.name, slave))
    base = unique(slug(name, "_"), dev)
    made = 0
    for k in range(more + 1):
        g = dict(f, name=base if not more else unique(f"{base}_{k + 1}", dev))
        if k:
            g["address"] = f["address"] + k * words
        clash = overlap(g, words, dev)
        if clash:
            report.append(_at(at, f"not converted: {name!r} reads the registers of "
                                  f"{clash!r}; rtupoll gives each register one meaning "
                                  f"(keep one, or use a bit field)"))
            continue
        g["_words"] = words
        dev.fields.append(g)
        dev.intervals.append(interval)
        made += 1
    return made


# Home Assistant before 2021.6: ``sensor: - platform: modbus`` with ``registers:``, and
# ``binary_sensor: - platform: modbus`` with ``inputs:``; the hub is named by ``hub``
_LEGACY_KEYS = {"register": "address", "register_type": "input_type",
                "reverse_order": "swap"}
LEGACY_SCAN = 30.0  # an entity platform's default scan interval in Home Assistant


def _legacy_platforms(tree: HaYaml, top: dict[str, Node], hubs: list[Hub],
                      report: list[str]) -> int:
    converted = 0
    for key, items, platform in (("sensor", "registers", "sensors"),
                                 ("binary_sensor", "inputs", "binary_sensors"),
                                 ("switch", "", "")):
        if key not in top or not tree.is_list(top[key]):
            continue
        for pnode in tree.sequence(top[key]):
            p = Entry(tree, pnode) if pnode.is_mapping else None
            if p is None or p.text("platform") != "modbus":
                continue
            if not platform:
                report.append(_at(pnode, "not converted: switch platform modbus (rtupoll "
                                         "polls; writes are 'rtupoll write' commands)"))
                continue
            interval = _seconds(p.text("scan_interval", str(LEGACY_SCAN)))
            if not p.has(items):
                report.append(_at(pnode, f"not converted: platform modbus without {items}"))
                continue
            for rnode in tree.sequence(p.node_of(items)):
                entry = _legacy_entry(tree, rnode)
                wanted = entry.text("hub", "default")
                hub = _hub_named(hubs, wanted)
                if hub is None:
                    report.append(_at(entry.node_of("hub"), f"not converted: "
                                                            f"{entry.text('name')!r}: no "
                                                            f"RTU hub named {wanted!r}"))
                    continue
                converted += _sensor(hub, entry, platform, report, interval)
            p.node_of("platform")
            p.report_rest(report, {})
    return converted


def _legacy_entry(tree: HaYaml, node: Node) -> Entry:
    """An old-style register, its keys renamed to today's (each node keeps its line)."""
    e = Entry(tree, node)
    renamed: dict[str, Node] = {}
    several = int(e.text("count", "1")) > 1  # reversing one register changes nothing
    for key, value in e.m.items():
        if key == "reverse_order":
            on = tree.text(value).lower() in ("true", "yes", "on")
            words = "word" if on and several else "none"
            value = Node(yaml.ScalarNode("tag:yaml.org,2002:str", words, value.node.start_mark,
                                         value.node.end_mark), value.file, value.path,
                         ConfigError)
        renamed[_LEGACY_KEYS.get(key, key)] = value
    e.m = renamed
    e.used = {"hub"}
    return e


def _hub_named(hubs: list[Hub], name: str) -> Hub | None:
    for hub in hubs:
        if hub.name == name:
            return hub
    return hubs[0] if len(hubs) == 1 else None


def _seconds(text: str) -> float:
    value = float(text)
    return int(value) if value.is_integer() else value


def overlap(f: dict[str, Any], words: int, dev: Device) -> str:
    a = f["address"]
    if isinstance(a, str):  # a bit field: shares its register only with other bit fields
        return ""
    for g in dev.fields:
        b = g["address"]
        if g["table"] != f["table"] or isinstance(b, str):
            continue
        if "byte" in f and "byte" in g and f["byte"] != g["byte"]:
            continue  # the two halves of one register
        if a < b + g["_words"] and b < a + words:
            return str(g["name"])
    return ""


def unique(name: str, dev: Device) -> str:
    names = {f["name"] for f in dev.fields}
    out, i = name, 2
    while out in names:
        out, i = f"{name}_{i}", i + 1
    return out


# letters NFKD cannot take apart: Cyrillic and Greek by common transliteration, and a few
# Latin ones, so that two meters named apart by one Cyrillic letter stay two names
_TRANSLIT = str.maketrans({
    **dict(zip("абвгдезийклмнопрстуфыэ", "abvgdezijklmnoprstufye", strict=True)),
    "ё": "yo", "ж": "zh", "х": "kh", "ц": "ts", "ч": "ch", "ш": "sh", "щ": "shch",  # noqa: RUF001
    "ъ": "", "ь": "", "ю": "yu", "я": "ya", "є": "ye", "і": "i", "ї": "yi", "ґ": "g",  # noqa: RUF001
    **dict(zip("αβγδεζηικλμνξοπρστυφωάέήίόύώϊϋς",
               "abgdezeiklmnxoprstyfoaeeiouoiys", strict=True)),
    "θ": "th", "χ": "ch", "ψ": "ps", "ß": "ss", "æ": "ae", "ø": "o", "œ": "oe", "ł": "l",
    "đ": "d", "ð": "d", "þ": "th", "°": "deg", "µ": "u", "²": "2", "³": "3", "%": "pct",
})


def ascii_name(text: str) -> str:
    """A name in ASCII letters that keeps what tells two names apart."""
    lowered = text.lower().translate(_TRANSLIT)
    return unicodedata.normalize("NFKD", lowered).encode("ascii", "ignore").decode()


def slug(text: str, sep: str) -> str:
    s = re.sub(r"[^a-z0-9]+", sep, ascii_name(text)).strip(sep)
    if not s or not s[0].isalpha():
        s = ("f" if sep == "_" else "x") + sep + s
    return s


def profile_text(dev: Device, hub: Hub, source: Path, origin: str = "Home Assistant") -> str:
    fast = device_interval(dev)
    fields = []
    for f, interval in zip(dev.fields, dev.intervals, strict=True):
        g = {k: v for k, v in f.items() if not k.startswith("_")}
        if interval > fast:
            g["interval"] = "once" if interval == ONCE else interval
        fields.append(g)
    doc: dict[str, Any] = {
        "id": dev.id, "vendor": f"{origin} import", "kind": "imported",
        "model": f"slave {dev.slave} on hub {hub.name}",
        "manual": f"{origin} modbus configuration {source.name}",
        "serial": {k: hub.serial[k] for k in ("baudrate", "parity", "stopbits")},
        "addressing": "pdu",
        "limits": {"max_registers": MAX_REGISTERS, "max_gap": 0,
                   "functions": [1, 2, 3, 4, 5, 6, 15, 16]},
        "fields": fields,
    }
    header = (f"# Imported from {origin}'s modbus configuration {source.name}: hub "
              f"{hub.name!r}, slave {dev.slave}.\n# Addresses are as {origin} sends "
              f"them (pdu). Check types and scales against the\n# device's manual, and add "
              f"identify rules so 'rtupoll scan' can recognise it.\n")
    return header + yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=100)


def device_interval(dev: Device) -> float:
    """How often the device is polled: its fastest field's interval (a device whose
    every field is read once only is looked at every ``IDLE`` seconds: nothing is due)."""
    return min((i for i in dev.intervals if i != ONCE), default=IDLE)


def site_text(hubs: Sequence[Hub], source: Path, origin: str = "Home Assistant") -> str:
    buses = []
    for hub in hubs:
        devices = []
        for dev in hub.devices.values():
            if not dev.fields:
                continue
            devices.append({"name": f"{slug(hub.name, '-')}-{dev.slave}", "profile": dev.id,
                            "address": dev.slave, "interval": device_interval(dev),
                            **hub.device_settings})
        if devices:
            bus: dict[str, Any] = {"name": slug(hub.name, "-"), "port": hub.port}
            bus.update(hub.serial)
            bus["devices"] = devices
            buses.append(bus)
    header = f"# Imported from {origin}'s modbus configuration {source.name}.\n"
    return header + yaml.safe_dump({"profiles": ["."], "buses": buses}, sort_keys=False,
                                   allow_unicode=True, width=100)
