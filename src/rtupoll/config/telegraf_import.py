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
    interval = _duration(str(data.get("agent", {}).get("interval", "10s")))
    report: list[str] = []
    hubs: list[Hub] = []
    converted = 0
    nreq = 0
    for k, plugin in enumerate(plugins):
        where = f"inputs.modbus[{k}]"
        line = lines.header("inputs.modbus", k)
        requests = plugin.get("request", [])
        hub = _hub(plugin, lines, line, where, report)
        if plugin.get("configuration_type", "register") != "request":
            report.append(lines.at(line, where, "not converted: configuration_type "
                                                "\"register\" (convert it to request style)"))
            hub = None
        for r, request in enumerate(requests):
            rline = lines.header("inputs.modbus.request", nreq)
            nreq += 1
            if hub is not None:
                converted += _request(hub, request, lines, rline,
                                      f"{where}.request[{r}]", report, interval)
        if hub is not None:
            hubs.append(hub)
    profiles = {dev.id: profile_text(dev, hub, path, ORIGIN)
                for hub in hubs for dev in hub.devices.values() if dev.fields}
    prefix = len(str(path)) + 1
    report.sort(key=lambda text: int(text[prefix:].split(":", 1)[0]))
    return Imported(profiles, site_text(hubs, path, ORIGIN), report, converted)


def _hub(plugin: dict[str, Any], lines: _Lines, line: int, where: str,
         report: list[str]) -> Hub | None:
    name = str(plugin.get("name", "modbus"))
    controller = str(plugin.get("controller", ""))
    mode = str(plugin.get("transmission_mode", "auto")).upper()
    serial = {"baudrate": int(plugin.get("baud_rate", 9600)),
              "parity": str(plugin.get("parity", "N")).upper(),
              "bytesize": int(plugin.get("data_bits", 8)),
              "stopbits": int(plugin.get("stop_bits", 1))}
    if controller.startswith("file://") and mode in ("RTU", "AUTO"):
        return Hub(name, controller[len("file://"):], serial)
    if controller.startswith("tcp://") and mode == "RTUOVERTCP":
        return Hub(name, controller, serial)
    report.append(lines.at(line, where, f"not converted: {name!r} uses {controller} in "
                                        f"{mode} mode; rtupoll speaks RTU, on a serial "
                                        f"port or an RTU-over-TCP gateway"))
    return None


def _duration(text: str) -> float:
    """Telegraf's "10s", "1m", "500ms" in seconds (10 when it cannot be read)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(ms|s|m|h)\s*", text)
    if not m:
        return 10
    value = float(m[1]) * {"ms": 0.001, "s": 1, "m": 60, "h": 3600}[m[2]]
    return int(value) if value.is_integer() else value


def _request(hub: Hub, request: dict[str, Any], lines: _Lines, line: int, where: str,
             report: list[str], interval: float) -> int:
    slave = int(request.get("slave_id", 1))
    table = _TABLES.get(str(request.get("register", "holding")))
    order = str(request.get("byte_order", "ABCD")).upper()
    if table is None or order not in ("ABCD", "BADC", "CDAB", "DCBA"):
        report.append(lines.at(line, where, f"not converted: register "
                                            f"{request.get('register')!r} / byte_order "
                                            f"{order!r}"))
        return 0
    dev = hub.devices.setdefault(slave, Device(hub.name, slave, prefix="telegraf"))
    made = 0
    for i, fld in enumerate(request.get("fields", [])):
        name = str(fld.get("name", f"field_{i}"))
        fline = lines.after(line, r"name\s*=\s*\"" + re.escape(name) + "\"")
        fwhere = f"{where}.fields[{i}]"
        if fld.get("omit"):
            continue
        f: dict[str, Any] = {"name": unique(slug(name, "_"), dev), "table": table,
                             "address": int(fld.get("address", 0))}
        words = 1
        if table in ("coil", "discrete"):
            f["type"] = "bool"
        else:
            dtype = str(fld.get("type", "INT16")).upper()
            t = _TYPES.get(dtype)
            if t is None:
                report.append(lines.at(fline, fwhere, f"not converted: {name!r}: type "
                                                      f"{dtype} has no rtupoll equivalent"))
                continue
            f["type"] = t
            if dtype == "BIT":
                f["address"] = f"{f['address']}:{int(fld.get('bit', 0))}:1"
            elif t in ("i8", "u8"):
                f["byte"] = "low" if dtype.endswith("L") else "high"
            elif t == "string":
                words = int(fld.get("length", 1))
                f["length"] = 2 * words
            else:
                words = DataType(t).words
                if words > 1 or order != "ABCD":
                    f["order"] = order
            scale = float(fld.get("scale", 1.0))
            if scale != 1:
                f["scale"] = int(scale) if scale.is_integer() else scale
        clash = overlap(f, words, dev)
        if clash:
            report.append(lines.at(fline, fwhere, f"not converted: {name!r} reads the "
                                                  f"registers of {clash!r}"))
            continue
        f["_words"] = words
        dev.fields.append(f)
        dev.intervals.append(interval)  # the agent's collection interval
        made += 1
    return made
