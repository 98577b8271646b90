"""Home Assistant ``modbus:`` YAML -> rtupoll profiles and a site file.

Home Assistant describes Modbus devices as hubs (a serial port or a gateway) with
sensors, each naming its slave, register, type and scaling. rtupoll keeps the device
knowledge (a profile) apart from where the device sits (a site file), so each
(hub, slave) pair becomes one profile and one site entry.

What converts: ``sensors`` and register/coil ``binary_sensors`` (``slave`` or
``device_address``, ``address``, ``input_type``, ``data_type``, ``count``, ``swap``,
``scale``, ``offset``, ``precision``, ``unit_of_measurement``, ``scan_interval``,
``state_class: total_increasing``, ``nan_value``, ``slave_count``/``virtual_count``).
What does not (``custom`` structures, Modbus TCP hubs, switches and other writable
entities, sensors that overlap another's registers, clamping options) is reported,
one line each, as ``file:line: path: not converted: why``; the rest still converts.
Pure: reads one file, returns text; the CLI writes the files.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rtupoll.config.yamlsrc import Node, load
from rtupoll.errors import ConfigError
from rtupoll.model.codec import DataType

_TYPES = {"int16": "i16", "uint16": "u16", "int32": "i32", "uint32": "u32", "int64": "i64",
          "uint64": "u64", "float32": "f32", "float64": "f64", "string": "string",
          "int8": "i8", "uint8": "u8"}
_LEGACY = {("int", 1): "i16", ("int", 2): "i32", ("int", 4): "i64", ("uint", 1): "u16",
           ("uint", 2): "u32", ("uint", 4): "u64", ("float", 2): "f32", ("float", 4): "f64"}
_SWAP = {"none": "ABCD", "byte": "BADC", "word": "CDAB", "word_byte": "DCBA"}
_PLATFORMS = ("sensors", "binary_sensors")
_UNSUPPORTED = ("switches", "climates", "covers", "lights", "fans")
DEFAULT_SCAN = 15.0  # Home Assistant's default scan_interval, seconds


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


@dataclass
class Imported:
    """The result: profile texts by id, the site file text, and what was not converted."""

    profiles: dict[str, str]
    site: str
    report: list[str]
    converted: int


def import_ha(path: Path) -> Imported:
    """Convert a Home Assistant configuration (a file with ``modbus:``, or the list of
    hubs itself) into profiles and a site file."""
    root = load(path, ConfigError)
    hubs_node = root
    if root.is_mapping:
        top = root.mapping()
        if "modbus" not in top:
            raise root.fail("no 'modbus:' section")
        hubs_node = top["modbus"]
    items = hubs_node.sequence() if hubs_node.is_list else [hubs_node]
    report: list[str] = []
    hubs: list[Hub] = []
    converted = 0
    for hnode in items:
        hub = _hub(hnode, report)
        if hub is None:
            continue
        hubs.append(hub)
        m = hnode.mapping()
        for key in _UNSUPPORTED:
            if key in m:
                report.append(_at(m[key], f"not converted: {key} (rtupoll polls; writes are "
                                           f"'rtupoll write' commands, not entities)"))
        for platform in _PLATFORMS:
            for snode in m[platform].sequence() if platform in m else []:
                converted += _sensor(hub, snode, platform, report)
    profiles = {}
    for hub in hubs:
        for dev in hub.devices.values():
            if dev.fields:
                profiles[dev.id] = profile_text(dev, hub, path)
    prefix = len(str(root.file)) + 1
    report.sort(key=lambda r: int(r[prefix:].split(":", 1)[0]))  # in file order
    return Imported(profiles, site_text(hubs, path), report, converted)


def _at(node: Node, message: str) -> str:
    return f"{node.file}:{node.line}: {node.path}: {message}"


def _text(m: dict[str, Node], key: str, default: str = "") -> str:
    return m[key].text() if key in m else default


def _hub(node: Node, report: list[str]) -> Hub | None:
    m = node.mapping()
    name = _text(m, "name", "modbus_hub")
    kind = _text(m, "type", "serial")
    if kind == "serial":
        if _text(m, "method", "rtu") != "rtu":
            report.append(_at(m["method"], "not converted: hub uses Modbus ASCII; rtupoll "
                                           "speaks RTU"))
            return None
        serial = {"baudrate": int(_text(m, "baudrate", "9600")),
                  "parity": _text(m, "parity", "N").upper(),
                  "bytesize": int(_text(m, "bytesize", "8")),
                  "stopbits": int(_text(m, "stopbits", "1"))}
        return Hub(name, _text(m, "port", "/dev/ttyUSB0"), serial)
    if kind == "rtuovertcp":
        return Hub(name, f"tcp://{_text(m, 'host')}:{_text(m, 'port', '502')}",
                   {"baudrate": 9600, "parity": "N", "bytesize": 8, "stopbits": 1})
    report.append(_at(m.get("type", node), f"not converted: hub {name!r} is type {kind} "
                                           f"(Modbus TCP/UDP); rtupoll speaks RTU, over a "
                                           f"serial port or an RTU-over-TCP gateway"))
    return None


def _sensor(hub: Hub, node: Node, platform: str, report: list[str]) -> int:
    """Add one HA sensor's field(s) to its device; returns how many fields it became."""
    m = node.mapping()
    name = _text(m, "name", f"sensor_{node.line}")

    def skip(key: str, why: str) -> int:
        report.append(_at(m.get(key, node), f"not converted: {name!r}: {why}"))
        return 0

    if "address" not in m:
        return skip("address", "no address")
    slave = int(_text(m, "slave", _text(m, "device_address", "0")), 0)
    if not 1 <= slave <= 247:
        report.append(_at(m.get("slave", m.get("device_address", node)),
                          f"{name!r}: slave {slave} is not a device address (Home "
                          f"Assistant's default 0 is broadcast); taken as 1"))
        slave = 1
    address = int(m["address"].text(), 0)
    table = _text(m, "input_type", "holding" if platform == "sensors" else "coil")
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
        dtype = _text(m, "data_type", "int16")
        count = int(_text(m, "count", "1"))
        t = _TYPES.get(dtype) or _LEGACY.get((dtype, count))
        if t is None:
            why = ("data_type custom (a struct format) has no rtupoll equivalent"
                   if dtype == "custom" else f"data_type {dtype} (count {count})")
            return skip("data_type", why)
        if t in ("i8", "u8"):
            return skip("data_type", f"{dtype}: Home Assistant's 8-bit types read a whole "
                                     f"register; rtupoll needs to know which byte")
        f["type"] = t
        wide = DataType(t).words > 1  # a number over several registers (not a string)
        words = count if t == "string" else DataType(t).words
        if t == "string":
            f["length"] = 2 * count
        swap = _text(m, "swap", "none")
        if swap not in _SWAP:
            return skip("swap", f"swap {swap}")
        if swap in ("word", "word_byte") and not wide:
            return skip("swap", f"swap {swap} on a one-register {dtype}")
        if swap != "none":
            f["order"] = _SWAP[swap]
        elif wide:
            f["order"] = "ABCD"
        for key, out in (("scale", "scale"), ("offset", "offset")):
            if key in m:
                value = float(m[key].text())
                if (key == "scale" and value != 1) or (key == "offset" and value):
                    f[out] = int(value) if value.is_integer() else value
        if "precision" in m:
            f["precision"] = int(m["precision"].text())
        if "unit_of_measurement" in m:
            f["unit"] = m["unit_of_measurement"].text()
        if _text(m, "state_class") == "total_increasing":
            f["counter"] = True
        if "nan_value" in m:
            f["sentinels"] = {int(m["nan_value"].text(), 0): "NOT_AVAILABLE"}
    if "device_class" in m:
        f["description"] = f"{name} ({m['device_class'].text()})"
    for key in ("min_value", "max_value", "zero_suppress"):
        if key in m:
            report.append(_at(m[key], f"{name!r}: {key} (Home Assistant clamps or zeroes "
                                      f"values) is not converted; the raw value is reported"))
    if "lazy_error_count" in m:
        report.append(_at(m["lazy_error_count"], f"{name!r}: lazy_error_count ignored "
                                                 f"(rtupoll reports every failed read)"))
    if table in ("holding", "input") and 30001 <= address <= 49999:
        report.append(_at(m["address"], f"{name!r}: address {address} looks like a 3xxxx/"
                                        f"4xxxx reference; Home Assistant sends it as "
                                        f"written (wire 0x{address:04X}), and so does this "
                                        f"profile. If the manual means register "
                                        f"{address % 10000}, use {address % 10000 - 1}"))
    dev = hub.devices.setdefault(slave, Device(hub.name, slave))
    n = int(_text(m, "slave_count", _text(m, "virtual_count", "0"))) + 1
    base = unique(slug(name, "_"), dev)
    interval = _seconds(_text(m, "scan_interval", str(DEFAULT_SCAN)))
    made = 0
    for k in range(n):
        g = dict(f, name=base if n == 1 else unique(f"{base}_{k + 1}", dev))
        if k:
            g["address"] = address + k * words
        clash = overlap(g, words, dev)
        if clash:
            report.append(_at(m["address"], f"not converted: {name!r} reads the registers "
                                             f"of {clash!r}; rtupoll gives each register "
                                             f"one meaning (keep one, or use a bit field)"))
            continue
        g["_words"] = words
        dev.fields.append(g)
        dev.intervals.append(interval)
        made += 1
    return made


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


def slug(text: str, sep: str) -> str:
    s = re.sub(r"[^a-z0-9]+", sep, text.lower()).strip(sep)
    if not s or not s[0].isalpha():
        s = ("f" if sep == "_" else "x") + sep + s
    return s


def profile_text(dev: Device, hub: Hub, source: Path, origin: str = "Home Assistant") -> str:
    fast = min(dev.intervals)
    fields = []
    for f, interval in zip(dev.fields, dev.intervals, strict=True):
        g = {k: v for k, v in f.items() if not k.startswith("_")}
        if interval > fast:
            g["interval"] = interval
        fields.append(g)
    doc: dict[str, Any] = {
        "id": dev.id, "vendor": f"{origin} import", "kind": "imported",
        "model": f"slave {dev.slave} on hub {hub.name}",
        "manual": f"{origin} modbus configuration {source.name}",
        "serial": {k: hub.serial[k] for k in ("baudrate", "parity", "stopbits")},
        "addressing": "pdu",
        "limits": {"max_registers": 125, "max_gap": 0,
                   "functions": [1, 2, 3, 4, 5, 6, 15, 16]},
        "fields": fields,
    }
    header = (f"# Imported from {origin}'s modbus configuration {source.name}: hub "
              f"{hub.name!r}, slave {dev.slave}.\n# Addresses are as {origin} sends "
              f"them (pdu). Check types and scales against the\n# device's manual, and add "
              f"identify rules so 'rtupoll scan' can recognise it.\n")
    return header + yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=100)


def site_text(hubs: Sequence[Hub], source: Path, origin: str = "Home Assistant") -> str:
    buses = []
    for hub in hubs:
        devices = []
        for dev in hub.devices.values():
            if not dev.fields:
                continue
            devices.append({"name": f"{slug(hub.name, '-')}-{dev.slave}", "profile": dev.id,
                            "address": dev.slave, "interval": min(dev.intervals)})
        if devices:
            bus: dict[str, Any] = {"name": slug(hub.name, "-"), "port": hub.port}
            bus.update(hub.serial)
            bus["devices"] = devices
            buses.append(bus)
    header = f"# Imported from {origin}'s modbus configuration {source.name}.\n"
    return header + yaml.safe_dump({"profiles": ["."], "buses": buses}, sort_keys=False,
                                   allow_unicode=True, width=100)
