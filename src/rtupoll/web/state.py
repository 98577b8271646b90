"""What the dashboard shows, as JSON: ``/api/state`` and the events of ``/api/events``.

One shape for both sources, so the page has one code path::

    {"mode": "poll" | "fleet", "time": WALL, "span": 3600, "step": 2,
     "gateways": [{"id", "title", "online", "version", "buses": [BUS...]}]}
    BUS    = {"name", "port", "serial", "utilisation", "port_error",
              "gateway": {"listen", "pending", "clients": [...]} | null, "devices": [DEVICE...]}
    DEVICE = {"key", "name", "profile", "model", "address", "bus", "state",
              "health": {...}, "fields": [FIELD...]}
    FIELD  = {"name", "label", "description", "unit", "kind", "precision", "value", "text",
              "severity", "status", "error", "badges": [{"name", "severity"}],
              "last": {"text", "time"} | null}

``kind`` is number, enum, flags or text; only numbers have a trend. Values, texts and
units are as every screen shows them (``model.interpret.display_value``: a temperature
in kelvin in °C, as in the live table and ``read``'s table); records keep the device's.
A field whose latest read failed has no ``value`` (never a stale one): ``status`` says
why, and ``last`` is its last good reading, with its time, for the page to show as such.
Times are wall-clock seconds since the epoch.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

from rtupoll.config.mqtt_settings import default_gateway_id
from rtupoll.jobs.stats import State, Status
from rtupoll.model.interpret import (
    display,
    display_unit,
    display_value,
    field_kind,
    reading_severity,
    severities,
    shown_precision,
    unlisted_severity,
)

if TYPE_CHECKING:
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading
    from rtupoll.model.profile import Field

SHORT_STATUS = {"timeout": "no reply", "garbled": "garbled reply", "skipped": "not read",
                "port": "port gone", "absent": "not in this variant"}


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("rtupoll")
    except PackageNotFoundError:
        return ""


_META: dict[int, tuple[Field, dict[str, Any]]] = {}  # id(field) -> (field, its meta)


def field_meta(f: Field) -> dict[str, Any]:
    """What the page shows of a field besides its value (a new dict, made once a field)."""
    got = _META.get(id(f))
    if got is None or got[0] is not f:
        text = (f.description or "").strip()
        got = _META[id(f)] = (f, {
            "name": f.name, "label": f.title,
            "description": text.splitlines()[0] if text else "",
            "unit": display_unit(f), "kind": field_kind(f), "precision": shown_precision(f)})
        if len(_META) > 100_000:  # profiles reloaded again and again: start afresh
            _META.clear()
    return dict(got[1])


def number(value: object) -> float | None:
    """The value a trend draws: a finite int or float (no bool, enum or text)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        f = float(value)
    except OverflowError:  # an integer beyond a float's range
        return None
    return f if math.isfinite(f) else None


def json_value(value: object) -> object:
    """Strict JSON: a NaN or infinite float is null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def field_state(f: Field, latest: Reading | None, last_good: Reading | None, *,
                meta: bool = True) -> dict[str, Any]:
    """``meta``: with what does not change (label, unit, kind ...); the events leave it
    out (the page has it from the snapshot) and carry only the name and the reading."""
    out: dict[str, Any] = field_meta(f) if meta else {"name": f.name}
    out.update(value=None, text="", severity="ok", status="", error="", badges=[],
               last=None)
    if latest is None:
        out["status"] = "waiting"
        return out
    out["time"] = latest.time
    fv = latest.value
    if fv is None:
        out["status"], out["error"] = latest.status.value, latest.error
        out["text"] = SHORT_STATUS.get(latest.status.value, latest.status.value)
        if latest.status is Status.ABSENT:
            out["severity"] = "info"
        if last_good is not None and last_good.value is not None:
            out["last"] = {"text": display(last_good.value)[0], "time": last_good.time}
        return out
    out["status"] = "ok"
    out["severity"] = fv.severity.value
    value, out["text"], _ = display_value(fv)  # kelvin as °C, as every screen shows it
    if fv.sentinel is not None:  # the device says there is no reading: no value
        out["badges"] = [{"name": fv.sentinel.name, "severity": fv.sentinel.severity.value}]
        return out
    out["value"] = json_value(value)
    if f.flags and isinstance(fv.value, list):
        named, unlisted = severities(f), unlisted_severity(f)
        out["badges"] = [{"name": n, "severity": reading_severity(n, named, unlisted).value}
                         for n in fv.value]
    elif f.enum and isinstance(fv.value, str):
        out["badges"] = [{"name": fv.value, "severity": fv.severity.value}]
    return out


class Clocks:
    """Wall and monotonic clocks read together: a monotonic deadline as a wall time."""

    def __init__(self, wall: float | None = None, mono: float | None = None) -> None:
        self.wall = time.time() if wall is None else wall
        self.mono = time.monotonic() if mono is None else mono

    def to_wall(self, mono: float) -> float:
        return self.wall + (mono - self.mono)


def health_state(dev: DevicePoller, clocks: Clocks, *, latency: bool = True
                 ) -> dict[str, Any]:
    """``latency=False`` (the events, after every cycle): without ``p50`` and ``p95``
    (sorting the reply times)."""
    cfg, st = dev.config, dev.stats
    waiting = st.state in (State.RETRYING, State.OFFLINE)
    out = {"ok": st.ok, "timeouts": st.timeouts, "garbled": st.garbled, "late": st.late,
           "exceptions": st.exception_count, "requests": st.requests, "cycles": st.cycles,
           "attempts": st.attempts, "timed_out_attempts": st.timed_out,
           "garbled_attempts": st.garbled_attempts, "retried": st.retried,
           "idle_gap": st.idle_gap, "idle_gap_source": st.gap_source,
           "failures": st.failures, "timeout": st.timeout,
           "timeout_source": st.timeout_source, "last_seen": st.last_good_time,
           "next_try": round(clocks.to_wall(dev.next_due), 2) if waiting else None,
           "interval": cfg.interval}
    if latency:
        out.update(p50=st.p50(), p95=st.p95())
    return out


def device_state(bus: str, dev: DevicePoller, clocks: Clocks) -> dict[str, Any]:
    cfg, st = dev.config, dev.stats
    p = cfg.profile
    fields = [field_state(f, st.latest.get(f.name), st.last_good.get(f.name))
              for f in cfg.fields]
    return {"key": cfg.name, "name": cfg.name, "profile": p.id,
            "model": " ".join(x for x in (p.vendor, p.model) if x), "address": cfg.address,
            "bus": bus, "state": st.state.value, "health": health_state(dev, clocks),
            "fields": fields}


_NEW = object()  # no signature sent yet


def reading_signature(latest: Reading | None, last_good: Reading | None) -> object:
    """What ``field_state`` shows of a reading, but its time: equal signatures give equal
    fields (the text follows from the value), without formatting anything."""
    if latest is None:
        return None
    fv = latest.value
    if fv is not None:
        return ("v", fv.value, fv.severity, fv.sentinel)
    return ("x", latest.status, latest.error, None if last_good is None else last_good.time)


def device_delta(dev: DevicePoller, clocks: Clocks, sent: dict[str, object]
                 ) -> dict[str, Any]:
    """A device's event after a cycle: its ``key``, ``state`` and ``health`` (without
    ``p50``/``p95``), ``times`` (every field's reading time, in the snapshot's field
    order; null before the first) and ``fields``: only those whose reading changed since
    the signatures in ``sent`` (which it updates), each without the unchanging parts
    and the time. Merged into the snapshot's device, it gives the snapshot's device."""
    cfg, st = dev.config, dev.stats
    latest, good = st.latest, st.last_good
    times: list[float | None] = []
    fields: list[dict[str, Any]] = []
    for f in cfg.fields:
        name = f.name
        r = latest.get(name)
        g = good.get(name)
        times.append(None if r is None else r.time)
        sig = reading_signature(r, g)
        if sent.get(name, _NEW) != sig:
            sent[name] = sig
            out = field_state(f, r, g, meta=False)
            out.pop("time", None)
            fields.append(out)
    return {"key": cfg.name, "state": st.state.value,
            "health": health_state(dev, clocks, latency=False), "times": times,
            "fields": fields}


def bus_state(bp: BusPoller, clocks: Clocks, served: dict[str, dict[str, Any]],
              *, devices: bool = True) -> dict[str, Any]:
    cfg = bp.config
    out: dict[str, Any] = {"name": cfg.name, "port": cfg.port, "serial": cfg.serial_text,
                           "utilisation": round(bp.load.utilisation(clocks.mono), 4),
                           "port_error": bp.port_error, "gateway": served.get(cfg.name)}
    if devices:
        out["devices"] = [device_state(cfg.name, d, clocks) for d in bp.devices]
    return out


def poll_state(scheduler: Scheduler, *, title: str, served: Iterable[dict[str, Any]] = (),
               gateway: str | None = None) -> dict[str, Any]:
    """The whole snapshot of a polling process (``served``: the gateway service's
    ``snapshot()``, its listeners' clients and queues)."""
    clocks = Clocks()
    by_bus = {s["bus"]: s for s in served}
    return {"mode": "poll", "time": clocks.wall, "span": _span(), "step": _step(),
            "gateways": [{"id": gateway or default_gateway_id(), "title": title, "online": True,
                          "version": version(),
                          "buses": [bus_state(bp, clocks, by_bus) for bp in scheduler.buses]}]}


def buses_event(scheduler: Scheduler, served: Sequence[dict[str, Any]], gateway: str
                ) -> dict[str, Any]:
    """Every bus's load and gateway clients, without the devices (a periodic event)."""
    clocks = Clocks()
    by_bus = {s["bus"]: s for s in served}
    return {"gateway": gateway, "time": clocks.wall,
            "buses": [bus_state(bp, clocks, by_bus, devices=False) for bp in scheduler.buses]}


def _span() -> float:
    from rtupoll.web.trend import SPAN

    return SPAN


def _step() -> float:
    from rtupoll.web.trend import STEP

    return STEP
