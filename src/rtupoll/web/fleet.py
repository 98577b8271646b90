"""``rtupoll web --mqtt URL``: every rtupoll gateway on a broker, on one page.

The viewer has no bus of its own. It subscribes to ``PREFIX/#`` and finds gateways by
their retained ``BASE/bridge/info`` (docs/mqtt.md: the gateway's id, version, base
topic, and each device's profile, address, bus and fields with label, unit, kind and
precision). Under each known BASE it reads::

    BASE/bridge/state           online | offline     the gateway itself (its last will)
    BASE/DEVICE/availability    online | offline     the device
    BASE/DEVICE                 {"FIELD": value, ..., "last_seen": "...",
                                 "_rtupoll": {"status": ..., "error": ...}}

Messages that arrive before their gateway's ``bridge/info`` wait (bounded) until it
comes. The page and its events have the shape of ``poll --http``'s
(``rtupoll.web.state``), with one section per gateway; a device's key is
``BASE/DEVICE``, so two buildings' devices at the same address never mix. Numeric
fields get the same trend rings, from the state messages as they arrive.
"""

from __future__ import annotations

import json
import logging
import math
import re
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from rtupoll.model.interpret import DISPLAY_UNITS, shown_number
from rtupoll.model.profile import is_difference
from rtupoll.ui.records import to_json
from rtupoll.web.server import Hub
from rtupoll.web.state import json_value, number
from rtupoll.web.trend import SPAN, STEP, TrendStore

log = logging.getLogger("rtupoll.web")
MAX_WAITING = 10_000  # messages held for gateways whose bridge/info has not come yet
INFO, BRIDGE, AVAIL = "/bridge/info", "/bridge/state", "/availability"
STATUS_KEY = "_rtupoll"  # rtupoll's own status in a state message (never a field)
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")  # as outputs.mqtt.topic_name


@dataclass
class Device:
    name: str
    info: dict[str, Any]
    availability: str = ""  # "" until the retained availability came
    values: dict[str, Any] = field(default_factory=dict)  # the latest state message
    time: float | None = None  # when it came (wall clock)
    at: float | None = None  # when it was read: its last_seen, else when it came


@dataclass
class Gateway:
    base: str
    id: str
    version: str = ""
    online: bool | None = None  # bridge/state; None: not seen
    devices: dict[str, Device] = field(default_factory=dict)  # topic level -> device


class Fleet:
    """What the broker says about every gateway (fed ``on_message``; a ``Source``)."""

    def __init__(self, prefix: str, where: str = "", *, clock: Any = time.time) -> None:
        self.prefix, self.where, self.clock = prefix, where, clock
        self.hub = Hub()
        self.trends = TrendStore(clock())
        self.gateways: dict[str, Gateway] = {}  # base -> gateway
        self.waiting: OrderedDict[str, bytes] = OrderedDict()  # topic -> payload
        self.broker = "connecting"

    # -- the MQTT side ------------------------------------------------------------

    def on_message(self, topic: str, payload: bytes) -> None:
        if topic.endswith(INFO):
            self._info(topic[:-len(INFO)], payload)
            return
        gw, rest = self._place(topic)
        if gw is None:
            if payload:
                self.waiting[topic] = payload
                self.waiting.move_to_end(topic)
                while len(self.waiting) > MAX_WAITING:
                    self.waiting.popitem(last=False)
            else:
                self.waiting.pop(topic, None)
            return
        text = payload.decode("utf-8", "replace").strip()
        if rest == BRIDGE[1:]:
            online = text == "online" if text else None
            if online != gw.online:
                gw.online = online
                self.hub.publish("state", "state", self._snapshot_json)
            return
        if rest.endswith(AVAIL) and rest.count("/") == 1:
            dev = gw.devices.get(rest[:-len(AVAIL)])
            if dev is not None and dev.availability != text:
                dev.availability = text
                self._publish(gw, dev)
            return
        if "/" not in rest:
            dev = gw.devices.get(rest)
            if dev is not None:
                self._state(gw, dev, payload)

    def set_broker(self, what: str) -> None:
        if what != self.broker:
            self.broker = what
            self.hub.publish("state", "state", self._snapshot_json)

    def _place(self, topic: str) -> tuple[Gateway | None, str]:
        best: Gateway | None = None
        for base, gw in self.gateways.items():
            if topic.startswith(base + "/") and (best is None or len(base) > len(best.base)):
                best = gw
        return (best, topic[len(best.base) + 1:]) if best is not None else (None, "")

    def _info(self, base: str, payload: bytes) -> None:
        if not payload.strip():  # a gateway that was removed for good
            if self.gateways.pop(base, None) is not None:
                self.trends.forget({k[0] for k in self.trends.rings
                                    if not k[0].startswith(base + "/")})
                self.hub.publish("state", "state", self._snapshot_json)
            return
        try:
            info = json.loads(payload)
            devices = info.get("devices", {})
            assert isinstance(devices, dict)
        except (ValueError, AttributeError, AssertionError):
            log.warning("%s%s: not a bridge/info object", base, INFO)
            return
        old = self.gateways.get(base)
        gw = Gateway(base, str(info.get("gateway") or base.rsplit("/", 1)[-1]),
                     str(info.get("version") or ""), old.online if old else None)
        for name, d in devices.items():
            if not isinstance(d, dict):
                continue
            # keyed by the device's topic level (``BASE/<key>`` is its state), with the
            # site's name for it under "name"
            level = _UNSAFE.sub("_", str(name))
            shown = str(d.get("name") or name)
            prev = old.devices.get(level) if old else None
            gw.devices[level] = Device(shown, d) if prev is None else \
                Device(shown, d, prev.availability, prev.values, prev.time, prev.at)
        self.gateways[base] = gw
        for topic in [t for t in self.waiting if t.startswith(base + "/")]:
            self.on_message(topic, self.waiting.pop(topic))
        self.hub.publish("state", "state", self._snapshot_json)

    def _state(self, gw: Gateway, dev: Device, payload: bytes) -> None:
        try:
            values = json.loads(payload) if payload.strip() else {}
        except ValueError:
            return
        if not isinstance(values, dict):
            return
        now = self.clock()
        seen = _epoch(values.get("last_seen"))
        at = seen if seen is not None and now - SPAN < seen <= now + 1 else now
        dev.values, dev.time, dev.at = values, now, at
        key = f"{gw.base}/{dev.name}"
        for name, meta in _fields(dev).items():
            if meta.get("kind", "number") == "number" and (v := number(values.get(name))) \
                    is not None:
                self.trends.add(key, name, at, shown_value(name, meta, v))
        self._publish(gw, dev)

    def _publish(self, gw: Gateway, dev: Device) -> None:
        self.hub.publish(f"d:{gw.base}/{dev.name}", "device", lambda: to_json(
            {"gateway": gw.id, "device": device_json(gw, dev)}))

    # -- the Source the server shows ---------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        gws = sorted(self.gateways.values(), key=lambda g: (g.id, g.base))
        return {"mode": "fleet", "title": self.where, "broker": self.broker,
                "time": self.clock(), "span": SPAN, "step": STEP,
                "gateways": [gateway_json(g) for g in gws]}

    def _snapshot_json(self) -> str:
        return to_json(self.snapshot())

    def trend(self, key: str, field: str) -> dict[str, Any]:
        return self.trends.series(key, field, self.clock())

    def metrics(self, accept: str) -> tuple[bytes, str] | None:
        return None


def _fields(dev: Device) -> dict[str, dict[str, Any]]:
    f = dev.info.get("fields")
    return {str(k): v for k, v in f.items() if isinstance(v, dict)} if isinstance(f, dict) \
        else {}


def _epoch(text: object) -> float | None:
    if not isinstance(text, str):
        return None
    try:
        return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


def gateway_json(gw: Gateway) -> dict[str, Any]:
    buses: dict[str, list[dict[str, Any]]] = {}
    for dev in gw.devices.values():
        buses.setdefault(str(dev.info.get("bus") or ""), []).append(device_json(gw, dev))
    return {"id": gw.id, "title": gw.id, "base": gw.base, "version": gw.version,
            "online": gw.online is not False,
            "buses": [{"name": b or "bus", "port": "", "serial": "", "utilisation": None,
                       "port_error": "", "gateway": None, "devices": devs}
                      for b, devs in buses.items()]}


def device_json(gw: Gateway, dev: Device) -> dict[str, Any]:
    values = dev.values
    got = values.get(STATUS_KEY)
    status: dict[str, Any] = got if isinstance(got, dict) else {}
    error = str(status.get("error") or values.get("error") or "")
    state = {"online": "online", "offline": "offline"}.get(dev.availability,
                                                           "online" if dev.time else "starting")
    fields = [field_json(name, meta, values, dev.at, error)
              for name, meta in _fields(dev).items()]
    if state == "offline" or gw.online is False:  # retained values are no readings now
        for f in fields:
            if f["status"] == "ok":
                f["last"] = {"text": f["text"], "time": dev.at}
                f.update(value=None, text="offline", status="offline", badges=[])
    info = dev.info
    return {"key": f"{gw.base}/{dev.name}", "name": dev.name,
            "profile": str(info.get("profile") or ""), "model": "",
            "address": info.get("address", ""), "bus": str(info.get("bus") or ""),
            "state": state, "error": error if state != "online" or not fields else "",
            "health": {"last_seen": _epoch(values.get("last_seen")), "next_try": None},
            "fields": fields}


def shown_value(name: str, meta: dict[str, Any], value: Any) -> Any:
    """A number as a person is shown it (``model.interpret.shown_number``): what the
    gateway published in its device's unit (``meta``: the field's ``bridge/info``)."""
    unit = str(meta.get("unit") or "")
    if unit not in DISPLAY_UNITS or isinstance(value, bool) \
            or not isinstance(value, (int, float)):
        return value
    precision = meta.get("precision") if isinstance(meta.get("precision"), int) else None
    label = str(meta.get("label") or "")
    return shown_number(unit, value, precision, difference=is_difference(name, label))


def field_json(name: str, meta: dict[str, Any], values: dict[str, Any], at: float | None,
               error: str) -> dict[str, Any]:
    kind = str(meta.get("kind") or "number")
    precision = meta.get("precision") if isinstance(meta.get("precision"), int) else None
    label = str(meta.get("label") or name.replace("_", " "))
    unit = str(meta.get("unit") or "")
    shown = DISPLAY_UNITS.get(unit)  # kelvin as °C, as a polling process's page shows it
    out: dict[str, Any] = {
        "name": name, "label": label,
        "description": "", "unit": shown[0] if shown else unit, "kind": kind,
        "precision": precision, "value": None, "text": "", "severity": "ok", "status": "",
        "error": "", "badges": [], "last": None}
    if at is None:
        out["status"] = "waiting"
        return out
    out["time"] = at
    if name not in values:
        out["status"], out["text"] = "absent", "not published"
        return out
    value = values[name]
    if value is None:
        out["status"], out["text"], out["error"] = "failed", "no reading", error
        return out
    value = shown_value(name, meta, value)
    out["status"], out["value"] = "ok", json_value(value)
    if kind == "flags" and isinstance(value, list):
        out["badges"] = [{"name": str(n), "severity": "info"} for n in value]
        out["text"] = ", ".join(map(str, value)) or "none"
    elif kind == "enum":
        out["badges"] = [{"name": str(value), "severity": "info"}]
        out["text"] = str(value)
    elif isinstance(value, float) and precision is not None and math.isfinite(value):
        out["text"] = f"{value:.{max(precision, 0)}f}"
    else:
        out["text"] = str(value) if not isinstance(value, float) or math.isfinite(value) \
            else ""
    return out
