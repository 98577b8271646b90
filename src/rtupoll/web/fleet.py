"""``rtupoll web --mqtt URL``: every rtupoll gateway on a broker, on one page.

The viewer has no bus of its own. It subscribes to ``PREFIX/#`` and finds gateways by
their retained ``BASE/bridge/info`` (docs/mqtt.md: the gateway's id, version, base
topic, and each device's profile, address, bus and fields with label, unit, kind and
precision, an enum's or flag set's names and a field's sentinels' with their
severities). Under each known BASE it reads::

    BASE/bridge/state           online | offline     the gateway itself (its last will)
    BASE/DEVICE/availability    online | offline     the device
    BASE/DEVICE                 {"FIELD": value, ..., "last_seen": "...",
                                 "_rtupoll": {"status": ..., "error": ...,
                                              "sentinels": {"FIELD": NAME}}}

Messages that arrive before their gateway's ``bridge/info`` wait (bounded in count
and bytes) until it comes. The page and its events have the shape of ``poll --http``'s
(``rtupoll.web.state``), with one section per gateway; a device's key is its state
topic, ``BASE/LEVEL`` (LEVEL: its one topic level, no ``/``), unique by construction:
two buildings' devices at the same address never mix, nor a device ``x/y`` of base
``site`` (level ``x_y``) and a device ``y`` of base ``site/x``. Numeric fields get the
same trend rings, from the state messages as they arrive; an enum's or flag set's
reading has the severity the dashboard gives it (``model.interpret.reading_severity``,
from the names in the state message and their severities in ``bridge/info``), and a
field whose value is a sentinel (null, with its name under ``sentinels``) is shown by
that name, a badge of its severity, as the dashboard shows it.

Every message is handled on its own (``handle``): one that cannot be (not JSON, a
number too large, the wrong types, too big) is dropped, counted in one log line a
minute, and the session goes on. Every size is bounded (docs/web.md, "Limits"):
``MAX_MESSAGE`` bytes a message, ``MAX_GATEWAYS``, ``MAX_DEVICES`` and ``MAX_FIELDS``
a gateway, ``MAX_FLEET_FIELDS`` in all, ``MAX_PRECISION`` decimals, ``MAX_NAMES`` names
with a severity a field and ``MAX_GATEWAY_NAMES`` a gateway, ``MAX_TEXT`` characters of
a name, label, unit or text value.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Any

from rtupoll.model.interpret import DISPLAY_UNITS, KINDS, reading_severity, shown_number
from rtupoll.model.profile import Severity, is_difference
from rtupoll.outputs.fleet import LAST_SEEN, SENTINELS, STATUS_KEY
from rtupoll.outputs.mqtt_state import topic_name
from rtupoll.refusals import Refusals
from rtupoll.ui.records import to_json
from rtupoll.web.server import Hub
from rtupoll.web.state import json_value, number
from rtupoll.web.trend import SPAN, STEP, TrendStore

log = logging.getLogger("rtupoll.web")
MAX_WAITING = 10_000  # messages held for gateways whose bridge/info has not come yet
MAX_WAITING_BYTES = 4 << 20  # and their bytes (topics and payloads)
MAX_MESSAGE = 1 << 20  # bytes a message may have (a bridge/info of 100 devices: ~300 kB)
MAX_GATEWAYS = 100
MAX_DEVICES = 1_000  # per gateway
MAX_FIELDS = 2_000  # per gateway (each numeric one has a trend ring, 15 kB at most)
MAX_FLEET_FIELDS = 10_000  # in all: trends of 152 MB at most
MAX_PRECISION = 6  # decimals a number is shown with at most
MAX_NAMES = 256  # names with a severity a field (an enum's values, a flag set's flags)
MAX_GATEWAY_NAMES = 20_000  # and a gateway (some 2 MB at most)
MAX_TEXT = 200  # characters of a name, label, unit, error or text value shown
INFO, BRIDGE, AVAIL = "/bridge/info", "/bridge/state", "/availability"


class Dropped(ValueError):
    """A message the viewer cannot use: dropped, counted, the session goes on."""


def short(value: object) -> str:
    """A text from the broker, at most ``MAX_TEXT`` characters."""
    text = str(value)
    return text if len(text) <= MAX_TEXT else text[:MAX_TEXT - 1] + "…"


@dataclass
class Device:
    name: str
    info: dict[str, Any]
    level: str = ""  # its topic level: BASE/LEVEL is its state, and its key
    availability: str = ""  # "" until the retained availability came
    values: dict[str, Any] = field(default_factory=dict)  # the latest state message
    sentinels: dict[str, str] = field(default_factory=dict)  # its fields' sentinels' names
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
        self.waiting_bytes = 0
        self.fields = 0  # fields of every gateway
        self.broker = "connecting"
        self.dropped = Refusals(f"--mqtt {where}" if where else "--mqtt", log,
                                noun="message", verb="dropped")

    # -- the MQTT side ------------------------------------------------------------

    def handle(self, topic: str, payload: bytes) -> bool:
        """One message from the broker, on its own: False when it was dropped (one log
        line a minute counts those), never an exception."""
        try:
            if len(payload) > MAX_MESSAGE:
                raise Dropped("larger than 1 MiB")
            self.on_message(topic, payload)
        except Dropped as exc:
            self.dropped.refused(str(exc))
            return False
        except Exception as exc:
            self.dropped.refused(f"{type(exc).__name__} (rtupoll's error: please report)")
            log.debug("%s: %s", topic, exc, exc_info=exc)
            return False
        return True

    def _hold(self, topic: str, payload: bytes) -> None:
        """A message of no known gateway (yet), held, bounded in count and bytes."""
        old = self.waiting.pop(topic, None)
        if old is not None:
            self.waiting_bytes -= len(topic) + len(old)
        if not payload:
            return
        self.waiting[topic] = payload
        self.waiting_bytes += len(topic) + len(payload)
        while self.waiting and (len(self.waiting) > MAX_WAITING or
                                self.waiting_bytes > MAX_WAITING_BYTES):
            t, p = self.waiting.popitem(last=False)
            self.waiting_bytes -= len(t) + len(p)

    def on_message(self, topic: str, payload: bytes) -> None:
        if topic.endswith(INFO):
            self._info(topic[:-len(INFO)], payload)
            return
        gw, rest = self._place(topic)
        if gw is None:
            self._hold(topic, payload)
            return
        text = short(payload[:MAX_TEXT * 4].decode("utf-8", "replace").strip())
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

    def _replace(self, base: str, new: Gateway | None) -> None:
        """The gateway at ``base`` is ``new`` now (None: gone for good): the fields
        counted again, and the trends of its devices that ``new`` has not dropped (a
        device's key is exactly ``base/level``: another gateway's, under a longer base,
        is never among them)."""
        old = self.gateways.pop(base, None)
        if old is not None:
            self.fields -= sum(len(d.info["fields"]) for d in old.devices.values())
            gone = {f"{base}/{lvl}" for lvl in old.devices} - \
                ({f"{base}/{lvl}" for lvl in new.devices} if new is not None else set())
            if gone:
                self.trends.forget({k[0] for k in self.trends.rings} - gone)
        if new is not None:
            self.gateways[base] = new
            self.fields += sum(len(d.info["fields"]) for d in new.devices.values())

    def _info(self, base: str, payload: bytes) -> None:
        if not payload.strip():  # a gateway that was removed for good
            if base in self.gateways:
                self._replace(base, None)
                self.hub.publish("state", "state", self._snapshot_json)
            return
        info = _loads(payload, "bridge/info")
        devices = info.get("devices", {}) if isinstance(info, dict) else None
        if not isinstance(devices, dict):
            raise Dropped("bridge/info not an object of devices")
        if base not in self.gateways and len(self.gateways) >= MAX_GATEWAYS:
            raise Dropped(f"bridge/info past {MAX_GATEWAYS} gateways")
        old = self.gateways.get(base)
        gw = Gateway(base, short(info.get("gateway") or base.rsplit("/", 1)[-1]),
                     short(info.get("version") or ""), old.online if old else None)
        room = min(MAX_FIELDS, MAX_FLEET_FIELDS - self.fields + (sum(
            len(d.info["fields"]) for d in old.devices.values()) if old else 0))
        cut = 0
        names = [MAX_GATEWAY_NAMES]  # names with a severity this gateway may still have
        for name, d in devices.items():
            if not isinstance(d, dict):
                continue
            # keyed by the device's topic level (``BASE/<level>`` is its state), with
            # the site's name for it under "name"
            level = topic_name(str(name))
            if len(gw.devices) >= MAX_DEVICES or len(level) > MAX_TEXT:
                cut += 1
                continue
            fields = _field_infos(d.get("fields"), room, names)
            cut += max(0, (len(d["fields"]) if isinstance(d.get("fields"), dict) else 0)
                       - len(fields))
            cut += sum(f.pop("cut", 0) for f in fields.values())
            room -= len(fields)
            meta = {"profile": short(d.get("profile") or ""), "bus": short(d.get("bus") or ""),
                    "address": d.get("address") if isinstance(d.get("address"), int) and
                    not isinstance(d.get("address"), bool) and 0 <= d["address"] <= 255 else "",
                    "fields": fields}
            shown = short(d.get("name") or name)
            prev = old.devices.get(level) if old else None
            gw.devices[level] = Device(shown, meta, level) if prev is None else \
                replace(prev, name=shown, info=meta, level=level)
        if cut:
            self.dropped.refused(f"devices, fields or severities past the limits ({MAX_DEVICES} "
                                 f"devices, {MAX_FIELDS} fields a gateway, {MAX_FLEET_FIELDS} "
                                 f"in all, {MAX_NAMES} names a field, {MAX_GATEWAY_NAMES} "
                                 "a gateway)")
        self._replace(base, gw)
        for topic in [t for t in self.waiting if t.startswith(base + "/")]:
            held = self.waiting.pop(topic)
            self.waiting_bytes -= len(topic) + len(held)
            self.handle(topic, held)
        self.hub.publish("state", "state", self._snapshot_json)

    def _state(self, gw: Gateway, dev: Device, payload: bytes) -> None:
        values = _loads(payload, "state") if payload.strip() else {}
        if not isinstance(values, dict):
            raise Dropped("state not a JSON object")
        fields = _fields(dev)
        sentinels = _sentinels(values.get(STATUS_KEY), fields)
        # only what is shown is kept: the device's fields, its status and time
        values = {k: _value(v) for k, v in values.items()
                  if k in fields or k in (STATUS_KEY, LAST_SEEN, "error")}
        now = self.clock()
        seen = _epoch(values.get(LAST_SEEN))
        at = seen if seen is not None and now - SPAN < seen <= now + 1 else now
        dev.values, dev.sentinels, dev.time, dev.at = values, sentinels, now, at
        key = f"{gw.base}/{dev.level}"
        for name, meta in fields.items():
            if meta.get("kind", "number") == "number" and (v := number(values.get(name))) \
                    is not None:
                self.trends.add(key, name, at, shown_value(name, meta, v))
        self._publish(gw, dev)

    def _publish(self, gw: Gateway, dev: Device) -> None:
        self.hub.publish(f"d:{gw.base}/{dev.level}", "device", lambda: to_json(
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


def _loads(payload: bytes, what: str) -> Any:
    try:
        return json.loads(payload)
    except RecursionError:
        raise Dropped(f"{what} nested too deep") from None
    except ValueError as exc:  # not UTF-8, not JSON, an integer of more than 4,300 digits
        raise Dropped(f"{what} not JSON ({type(exc).__name__})") from None


def _value(v: object) -> object:
    """A state message's value as kept: a number (a float's range: a larger integer is
    no reading), a short text, a list of short texts (flags), or None."""
    if isinstance(v, bool) or v is None:
        return v
    if isinstance(v, int):
        return v if abs(v) < 1 << 63 else None
    if isinstance(v, float):
        return v
    if isinstance(v, str):
        return short(v)
    if isinstance(v, list):
        return [short(x) for x in v[:64] if isinstance(x, (str, int)) and
                not isinstance(x, bool)]
    if isinstance(v, dict):  # rtupoll's own status
        return {short(k)[:40]: short(x) for k, x in list(v.items())[:8]
                if isinstance(x, (str, int, float)) or x is None}
    return None


def _sentinels(status: object, fields: dict[str, Any]) -> dict[str, str]:
    """A state message's ``_rtupoll.sentinels``: each of the device's fields whose value
    is a sentinel, with its name (bounded: the device's fields, a short name)."""
    got = status.get(SENTINELS) if isinstance(status, dict) else None
    if not isinstance(got, dict):
        return {}
    return {k: short(v) for k, v in got.items() if k in fields and isinstance(v, str)}


def _field_infos(got: object, room: int, names: list[int]) -> dict[str, dict[str, Any]]:
    """A device's fields from its bridge/info, at most ``room``, each with its label,
    unit, kind, precision and names' severities (an enum's, a flag set's, its
    sentinels') checked and bounded (``names``: how many names the gateway may still
    have; a field whose names do not fit has none, and ``cut``)."""
    out: dict[str, dict[str, Any]] = {}
    if not isinstance(got, dict):
        return out
    for k, v in got.items():
        if len(out) >= room:
            break
        if not isinstance(v, dict):
            continue
        p = v.get("precision")
        precision = min(max(p, 0), MAX_PRECISION) if isinstance(p, int) and \
            not isinstance(p, bool) else None
        kind = v.get("kind") if v.get("kind") in KINDS else "number"
        info = {"label": short(v.get("label") or ""), "unit": short(v.get("unit") or ""),
                "kind": kind, "precision": precision, **_severities(v, names)}
        sentinels = _named(v.get("sentinels"), names)
        if sentinels is None:
            info["cut"] = info.get("cut", 0) + 1
        elif sentinels:
            info["sentinels"] = sentinels
        out[short(k)] = info
    return out


_SEVERITY = {s.value: s for s in Severity}


def _severities(v: dict[str, Any], room: list[int]) -> dict[str, Any]:
    """A field's ``severities`` (name -> severity) and ``unlisted`` from its bridge/info,
    checked; none from a gateway that sends none (its badges are ``info``), nor past
    the limits (``cut``: 1)."""
    got, unlisted = v.get("severities"), _SEVERITY.get(str(v.get("unlisted")))
    if not isinstance(got, dict) or unlisted is None:
        return {}
    named = _named(got, room)
    return {"cut": 1} if named is None else {"severities": named, "unlisted": unlisted}


def _named(got: object, room: list[int]) -> dict[str, Severity] | None:
    """Names with their severities from bridge/info (``severities``, ``sentinels``),
    checked: none when not an object; None past the limits (``MAX_NAMES`` a field,
    ``room[0]`` the gateway's, which it takes them from)."""
    if not isinstance(got, dict):
        return {}
    if len(got) > min(MAX_NAMES, room[0]):
        return None
    room[0] -= len(got)
    return {name: s for name, sev in got.items()
            if (s := _SEVERITY.get(str(sev))) is not None and len(name) <= MAX_TEXT}


def _fields(dev: Device) -> dict[str, dict[str, Any]]:
    f: dict[str, dict[str, Any]] = dev.info["fields"]
    return f


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
    fields = [field_json(name, meta, values, dev.at, error, dev.sentinels.get(name))
              for name, meta in _fields(dev).items()]
    if state == "offline" or gw.online is False:  # retained values are no readings now
        for f in fields:
            if f["status"] == "ok":
                f["last"] = {"text": f["text"], "time": dev.at}
                f.update(value=None, text="offline", status="offline", severity="ok",
                         badges=[])
    info = dev.info
    return {"key": f"{gw.base}/{dev.level}", "name": dev.name,
            "profile": str(info.get("profile") or ""), "model": "",
            "address": info.get("address", ""), "bus": str(info.get("bus") or ""),
            "state": state, "error": error if state != "online" or not fields else "",
            "health": {"last_seen": _epoch(values.get(LAST_SEEN)), "next_try": None},
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
               error: str, sentinel: str | None = None) -> dict[str, Any]:
    """A field as the page shows it (``web.state``'s shape) from its ``bridge/info``
    (``meta``) and the state message (``values``; ``sentinel``: the name of the sentinel
    its null value is, from the message's ``_rtupoll.sentinels``)."""
    kind = str(meta.get("kind") or "number")
    precision = meta.get("precision")
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
        out["status"], out["text"], out["severity"] = "absent", "not published", "info"
        return out
    value = values[name]
    if value is None and sentinel is not None:  # the device says there is no reading
        got: dict[str, Severity] = meta.get("sentinels") or {}
        sev = got[sentinel].value if sentinel in got else "info"  # unknown to it: neutral
        out.update(status="ok", text=sentinel, severity=sev,
                   badges=[{"name": sentinel, "severity": sev}])
        return out
    if value is None:
        out["status"], out["text"], out["error"] = "failed", "no reading", error
        return out
    value = shown_value(name, meta, value)
    out["status"], out["value"] = "ok", json_value(value)
    named: dict[str, Severity] | None = meta.get("severities")
    unlisted: Severity = meta.get("unlisted", Severity.WARNING)

    def severity(names: object) -> str:  # without bridge/info's severities: neutral
        return "info" if named is None else reading_severity(names, named, unlisted).value

    if kind in ("enum", "flags") and named is not None:
        out["severity"] = severity(value)
    if kind == "flags" and isinstance(value, list):
        out["badges"] = [{"name": str(n), "severity": severity(n)} for n in value]
        out["text"] = ", ".join(map(str, value)) or "none"
    elif kind == "enum":
        out["badges"] = [{"name": str(value), "severity": severity(value)}]
        out["text"] = str(value)
    elif isinstance(value, float) and precision is not None and math.isfinite(value):
        out["text"] = f"{value:.{max(precision, 0)}f}"
    else:
        out["text"] = str(value) if not isinstance(value, float) or math.isfinite(value) \
            else ""
    return out
