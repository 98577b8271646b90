"""Telegraf ``[[inputs.modbus]]`` (request style) -> rtupoll profiles and a site file.

Each ``[[inputs.modbus]]`` plugin is a hub (``controller`` = a serial port or an
RTU-over-TCP gateway); each ``[[inputs.modbus.request]]`` names a slave, a register
table, a byte order and its fields. Every (plugin, slave) pair becomes one profile, as
for Home Assistant imports (``ha_import``), with the same site file.

TOML readers give no line numbers, so the report finds them in the text: the n-th
request header, and a field's ``name = "..."`` inside its request. What does not
convert (the older ``configuration_type = "register"`` style, Modbus TCP/ASCII,
``FLOAT16``, a field overlapping another) is reported as ``file:line: path: why``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from rtupoll.config.ha_import import (
    Device,
    Hub,
    Imported,
    overlap,
    profile_text,
    site_text,
    slug,
    unique,
)
from rtupoll.errors import ConfigError, UsageError
from rtupoll.model.codec import DataType

_TYPES = {"INT16": "i16", "UINT16": "u16", "INT32": "i32", "UINT32": "u32", "INT64": "i64",
          "UINT64": "u64", "FLOAT32": "f32", "FLOAT64": "f64", "STRING": "string",
          "INT8L": "i8", "INT8H": "i8", "UINT8L": "u8", "UINT8H": "u8", "BIT": "u16"}
_TABLES = {"holding": "holding", "input": "input", "coil": "coil", "discrete": "discrete"}
ORIGIN = "Telegraf"


def _toml(path: Path) -> dict[str, Any]:
    import importlib

    toml: Any = None
    for module in ("tomllib", "tomli"):  # the standard library from Python 3.11 on
        try:
            toml = importlib.import_module(module)
            break
        except ImportError:
            continue
    if toml is None:
        raise UsageError("reading Telegraf's TOML needs Python 3.11 or the 'tomli' package")
    try:
        data: dict[str, Any] = toml.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", file=str(path)) from None
    except toml.TOMLDecodeError as exc:
        raise ConfigError(f"TOML syntax: {exc}", file=str(path)) from None
    return data


class _Lines:
    """Where things are in the file, for the report."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.lines = path.read_text(encoding="utf-8").splitlines()

    def header(self, pattern: str, n: int) -> int:
        """Line (1-based) of the n-th ``[[pattern]]`` header; 0 when not found."""
        rx = re.compile(r"^\s*\[\[\s*" + re.escape(pattern) + r"\s*\]\]")
        hits = [i + 1 for i, line in enumerate(self.lines) if rx.match(line)]
        return hits[n] if n < len(hits) else 0

    def after(self, start: int, rx: str) -> int:
        """First line after line ``start`` matching ``rx``, before the next ``[[`` header
        (``start`` itself when there is none)."""
        for i in range(start, len(self.lines)):
            if self.lines[i].lstrip().startswith("[["):
                break
            if re.search(rx, self.lines[i]):
                return i + 1
        return start

    def at(self, line: int, where: str, message: str) -> str:
        return f"{self.path}:{line}: {where}: {message}"


def import_telegraf(path: Path) -> Imported:
    data = _toml(path)
    plugins = data.get("inputs", {}).get("modbus")
    if not isinstance(plugins, list) or not plugins:
        raise ConfigError("no [[inputs.modbus]] section", file=str(path), line=1)
    lines = _Lines(path)
    agent = _duration(str(data.get("agent", {}).get("interval", "10s")))
    report: list[str] = []
    hubs: list[Hub] = []
    converted = 0
    seen = {"request": 0, "metric": 0}  # headers of each kind met so far, for their lines
    for k, plugin in enumerate(plugins):
        where = f"inputs.modbus[{k}]"
        line = lines.header("inputs.modbus", k)
        hub = _hub(plugin, lines, line, where, report)
        interval = agent
        if "interval" in plugin:  # the plugin's own collection interval wins over [agent]'s
            interval = _duration(str(plugin["interval"]))
        style = str(plugin.get("configuration_type", "register"))
        if style not in _STYLES:
            report.append(lines.at(line, where, f"not converted: configuration_type "
                                                f"{style!r} (Telegraf knows register, "
                                                f"request and metric)"))
            hub = None
        groups: list[tuple[dict[str, Any], int, str]] = []
        if style in seen:
            for r, group in enumerate(plugin.get(style, [])):
                groups.append((group, lines.header(f"inputs.modbus.{style}", seen[style]),
                               f"{where}.{style}[{r}]"))
                seen[style] += 1
        elif style == "register":
            groups.append((_register_style(plugin), line, where))
        if hub is not None:
            for group, gline, gwhere in groups:
                converted += _group(hub, group, style, lines, gline, gwhere, report, interval)
            hubs.append(hub)
            _rest(plugin, _PLUGIN_KEYS | {style}, _PLUGIN_NOTES, lines, line, where, report)
    profiles = {dev.id: profile_text(dev, hub, path, ORIGIN)
                for hub in hubs for dev in hub.devices.values() if dev.fields}
    report.sort(key=_file_order)
    return Imported(profiles, site_text(hubs, path, ORIGIN), report, converted)


_STYLES = ("register", "request", "metric")
_PLUGIN_KEYS = {"name", "controller", "transmission_mode", "baud_rate", "data_bits",
                "parity", "stop_bits", "configuration_type", "interval", "timeout",
                "slave_id", "coils", "discrete_inputs", "holding_registers",
                "input_registers"}
_PLUGIN_NOTES = {
    "busy_retries": "rtupoll retries every unanswered request (the device's retries)",
    "busy_retries_wait": "rtupoll waits the line's silence between tries",
    "pause_between_requests": "rtupoll keeps the 3.5-character silence between frames and "
                              "learns each device's timing; a device that needs more gets "
                              "limits.turnaround in its profile",
    "pause_after_connect": "rtupoll needs no pause after opening the port",
    "close_connection_after_gather": "rtupoll keeps the port open",
    "optimization": "rtupoll plans its own block reads from the profile's limits",
    "optimization_max_register_fill": "rtupoll plans its own block reads",
    "debug_connection": "rtupoll's -v logs every frame",
    "workarounds": "Telegraf's device workarounds have no rtupoll counterpart",
    "tags": "rtupoll tags every record with the device's name, profile and address",
    "fieldpass": "Telegraf drops fields after reading; rtupoll polls every imported field "
                 "(remove the ones you do not want from the profile or the site file)",
    "fielddrop": "Telegraf drops fields after reading; rtupoll polls every imported field",
    "fieldinclude": "Telegraf drops fields after reading; rtupoll polls every imported "
                    "field",
    "fieldexclude": "Telegraf drops fields after reading; rtupoll polls every imported "
                    "field",
    "name_override": "rtupoll's records name the device, not a measurement",
    "name_prefix": "rtupoll's records name the device, not a measurement",
    "name_suffix": "rtupoll's records name the device, not a measurement",
    "measurement": "rtupoll's records name the device, not a measurement",
}
_GROUP_KEYS = {"slave_id", "byte_order", "register", "fields"}
_FIELD_KEYS = {"address", "name", "type", "scale", "omit", "length", "bit", "register",
               "output", "byte_order", "data_type"}


def _file_order(note: str) -> tuple[str, int]:
    m = re.match(r"(.*?):(\d+): ", note)
    return (m[1], int(m[2])) if m else (note, 0)


def _rest(table: dict[str, Any], known: set[str], why: dict[str, str], lines: _Lines,
          line: int, where: str, report: list[str], name: str = "") -> None:
    """List every key of a table that did not carry over (nothing dropped silently)."""
    for key in table:
        if key in known:
            continue
        kline = lines.after(line, r"^\s*" + re.escape(key) + r"\s*=") if name == "" else line
        who = f"{name!r}: " if name else ""
        reason = why.get(key, "rtupoll has no such setting")
        report.append(lines.at(kline, f"{where}.{key}", f"not carried over: {who}{key} "
                                                         f"({reason})"))


def _register_style(plugin: dict[str, Any]) -> dict[str, Any]:
    """The original style's four lists as one group of fields, each with its table."""
    fields = []
    for key, table in (("coils", "coil"), ("discrete_inputs", "discrete"),
                       ("holding_registers", "holding"), ("input_registers", "input")):
        for fld in plugin.get(key, []):
            fields.append({**fld, "register": table, "_list": key})
    return {"slave_id": plugin.get("slave_id", 1), "fields": fields, "_style": "register"}


def _hub(plugin: dict[str, Any], lines: _Lines, line: int, where: str,
         report: list[str]) -> Hub | None:
    name = str(plugin.get("name", "modbus"))
    controller = str(plugin.get("controller", ""))
    mode = str(plugin.get("transmission_mode", "auto")).upper()
    serial = {"baudrate": int(plugin.get("baud_rate", 9600)),
              "parity": str(plugin.get("parity", "N")).upper(),
              "bytesize": int(plugin.get("data_bits", 8)),
              "stopbits": int(plugin.get("stop_bits", 1))}
    hub = None
    if controller.startswith("file://") and mode in ("RTU", "AUTO"):
        hub = Hub(name, controller[len("file://"):], serial)
    elif controller.startswith("tcp://") and mode == "RTUOVERTCP":
        hub = Hub(name, controller, serial)
    if hub is None:
        report.append(lines.at(line, where, f"not converted: {name!r} uses {controller} in "
                                            f"{mode} mode; rtupoll speaks RTU, on a serial "
                                            f"port or an RTU-over-TCP gateway"))
        return None
    if "timeout" in plugin:  # Telegraf's wait for each reply: rtupoll's longest wait
        hub.device_settings["timeout_ceiling"] = _duration(str(plugin["timeout"]))
    return hub


def _duration(text: str) -> float:
    """Telegraf's "10s", "1m", "500ms" in seconds (10 when it cannot be read)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(ms|s|m|h)\s*", text)
    if not m:
        return 10
    value = float(m[1]) * {"ms": 0.001, "s": 1, "m": 60, "h": 3600}[m[2]]
    return int(value) if value.is_integer() else value


# the original style's byte orders: two letters for one register, eight for four
_ORDERS = {"AB": "ABCD", "BA": "BADC", "ABCDEFGH": "ABCD", "HGFEDCBA": "DCBA",
           "BADCFEHG": "BADC", "GHEFCDAB": "CDAB"}
_REGISTER_TYPES = {"FLOAT32-IEEE": "f32", "FLOAT64-IEEE": "f64", "FLOAT16-IEEE": "FLOAT16"}
_FIXED = {("FIXED", 1): "i16", ("FIXED", 2): "i32", ("FIXED", 4): "i64",
          ("UFIXED", 1): "u16", ("UFIXED", 2): "u32", ("UFIXED", 4): "u64"}


def _group(hub: Hub, group: dict[str, Any], style: str, lines: _Lines, line: int,
           where: str, report: list[str], interval: float) -> int:
    """One request (or metric, or the original style's lists) of one slave."""
    slave = int(group.get("slave_id", 1))
    order = _ORDERS.get(str(group.get("byte_order", "ABCD")).upper(),
                        str(group.get("byte_order", "ABCD")).upper())
    default_table = _TABLES.get(str(group.get("register", "holding")))
    if default_table is None or order not in ("ABCD", "BADC", "CDAB", "DCBA"):
        report.append(lines.at(line, where, f"not converted: register "
                                            f"{group.get('register')!r} / byte_order "
                                            f"{group.get('byte_order')!r}"))
        return 0
    dev = hub.devices.setdefault(slave, Device(hub.name, slave, prefix="telegraf"))
    made = 0
    for i, fld in enumerate(group.get("fields", [])):
        name = str(fld.get("name", f"field_{i}"))
        fline = lines.after(line, r"name\s*=\s*\"" + re.escape(name) + "\"")
        fwhere = (f"{where}.{fld['_list']}" if "_list" in fld else f"{where}.fields") + f"[{i}]"
        if fld.get("omit"):
            continue
        table = _TABLES.get(str(fld.get("register", default_table)), default_table)
        forder = _ORDERS.get(str(fld.get("byte_order", order)).upper(),
                             str(fld.get("byte_order", order)).upper())
        done = _field(fld, name, table, forder, style, dev, lines, fline, fwhere, report)
        if done is None:
            continue
        f, words = done
        clash = overlap(f, words, dev)
        if clash:
            report.append(lines.at(fline, fwhere, f"not converted: {name!r} reads the "
                                                  f"registers of {clash!r}"))
            continue
        _rest({k: v for k, v in fld.items() if not k.startswith("_")}, _FIELD_KEYS,
              _PLUGIN_NOTES, lines, fline, fwhere, report, name)
        f["_words"] = words
        dev.fields.append(f)
        dev.intervals.append(interval)
        made += 1
    _rest({k: v for k, v in group.items() if not k.startswith("_")}, _GROUP_KEYS,
          _PLUGIN_NOTES, lines, line, where, report)
    return made


def _field(fld: dict[str, Any], name: str, table: str, order: str, style: str, dev: Device,
           lines: _Lines, line: int, where: str,
           report: list[str]) -> tuple[dict[str, Any], int] | None:
    """One Telegraf field as a profile field and its register count (None: reported)."""
    address = fld.get("address", 0)
    if isinstance(address, list):  # the original style lists the registers it reads
        if not address or address != list(range(address[0], address[0] + len(address))):
            report.append(lines.at(line, where, f"not converted: {name!r}: registers "
                                                f"{address} are not consecutive"))
            return None
        count, address = len(address), address[0]
    else:
        count = 0
    f: dict[str, Any] = {"name": unique(slug(name, "_"), dev), "table": table,
                         "address": int(address)}
    if slug(name, "_") != name:
        f["description"] = name
    if table in ("coil", "discrete"):
        f["type"] = "bool"
        return f, 1
    dtype = str(fld.get("data_type" if style == "register" else "type",
                        "INT16")).upper()
    t = _FIXED.get((dtype if dtype != "FLOAT32" else "UFIXED", count or 1)) \
        if style == "register" and dtype in ("FIXED", "UFIXED", "FLOAT32") else \
        _REGISTER_TYPES.get(dtype) or _TYPES.get(dtype)
    if t is None or t == "FLOAT16":
        report.append(lines.at(line, where, f"not converted: {name!r}: type {dtype} has "
                                            f"no rtupoll equivalent"))
        return None
    f["type"] = t
    words = 1
    if dtype == "BIT":
        f["address"] = f"{f['address']}:{int(fld.get('bit', 0))}:1"
    elif t in ("i8", "u8"):
        f["byte"] = "low" if dtype.endswith("L") else "high"
    elif t == "string":
        words = int(fld.get("length", count or 1))
        f["length"] = 2 * words
        if order in ("BADC", "DCBA"):
            f["order"] = "BADC"
    else:
        words = DataType(t).words
        if words > 1 or order != "ABCD":
            f["order"] = order if words > 1 else ("BADC" if order in ("BADC", "DCBA")
                                                  else "ABCD")
    if count and count != words:
        report.append(lines.at(line, where, f"not converted: {name!r}: {dtype} takes "
                                            f"{words} register(s), the address lists "
                                            f"{count}"))
        return None
    scale = float(fld.get("scale", 1.0))
    if scale not in (0.0, 1.0):  # Telegraf treats a scale of 0 as no scaling
        f["scale"] = int(scale) if scale.is_integer() else scale
    output = str(fld.get("output", "")).upper()
    if output in ("INT64", "UINT64") and t != "string":
        f["precision"] = 0
        report.append(lines.at(line, where, f"{name!r}: output {output}: Telegraf stores "
                                            f"a whole number; the profile shows the value "
                                            f"with precision 0"))
    return f, words
