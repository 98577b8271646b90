"""Readings -> the MQTT messages that carry them. Pure: no broker, no library, a clock given.

Per device, ``BASE/DEVICE`` carries one JSON object with **every polled field** (the
keys Home Assistant's discovery names), each at its latest value: this scan's, or for a
field on a slower ``interval`` the one it was last read with. A field whose read
failed this scan is ``null`` (never a stale value), as is a field the device's
generation lacks. Then ``last_seen`` and ``_rtupoll``, rtupoll's own status, under a key
no profile field can take:

    {"co2": 800, ..., "last_seen": "2026-...Z", "_rtupoll": {"status": "ok", "error": null}}

``status`` is ``ok`` (every field has its value: none is null for a failed read, this
scan's or, for a slow field not read in this one, its last, nor for the device's "no
value": a sentinel, a NaN), ``partial`` (some failed or have no value) or ``failed``
(none read this scan); ``error`` is the first failure's line (null when ``ok``). A field
this generation of the device lacks is null and no failure. A field whose latest value
is one of its profile's sentinels is null, and ``sentinels`` (only while there is one)
names it, as the dashboard shows it: ``"sentinels": {"temperature_1": "NO_SENSOR"}``.
``BASE/DEVICE/availability`` is published when it changes; ``BASE/DEVICE/FIELD``
plain values when ``field_topics`` is on.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rtupoll.jobs.stats import Status
from rtupoll.model.record import iso_time
from rtupoll.outputs.fleet import LAST_SEEN, SENTINELS, STATUS_KEY
from rtupoll.outputs.mqtt_commands import value_of
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.config.mqtt_settings import MqttSettings
    from rtupoll.config.site import DeviceConfig
    from rtupoll.jobs.stats import Reading


_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


def topic_name(device: str) -> str:
    """A device's topic level: its name, with anything but ``[A-Za-z0-9_.-]`` as ``_``."""
    return _UNSAFE.sub("_", device)


@dataclass(frozen=True)
class Out:
    """One message to publish (the service adds the QoS)."""

    topic: str
    payload: str
    retain: bool


class StatePublisher:
    """What the MQTT service publishes for readings; remembers what a reconnect repeats."""

    def __init__(self, settings: MqttSettings, topics: dict[str, str],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.settings = settings
        self.topics = topics  # device name -> topic level
        self._clock = clock
        self.state: dict[str, str] = {}  # topic level -> its latest state payload
        self.avail: dict[str, str] = {}  # topic level -> online/offline
        self._values: dict[str, dict[str, Any]] = {}  # topic level -> field -> latest value
        self._failed: dict[str, dict[str, str]] = {}  # topic level -> field -> why it is null
        self._sentinels: dict[str, dict[str, str]] = {}  # topic level -> field -> its sentinel
        self._compared: dict[str, Any] = {}  # on_change: what was last published
        self._sent_at: dict[str, float] = {}
        self.forced: set[str] = set()  # a get asked for the next state, changed or not

    def topic(self, device: str) -> str:
        return self.topics.get(device) or topic_name(device)

    def readings(self, cfg: DeviceConfig, online: bool, last_good: float | None,
                 readings: Iterable[Reading]) -> list[Out]:
        """One scan's readings of a device -> its messages (none when ``on_change`` has
        nothing new to say)."""
        s, t = self.settings, self.topic(cfg.name)
        base = s.base
        out: list[Out] = []
        avail = "online" if online else "offline"
        if self.avail.get(t) != avail:
            self.avail[t] = avail
            out.append(Out(f"{base}/{t}/availability", avail, True))
        known = self._values.get(t, {})
        values: dict[str, Any] = {f.name: known.get(f.name) for f in cfg.fields}
        # fields whose latest read failed, with why: null until a read gives them a value
        was = self._failed.get(t, {})
        failed = {f.name: was[f.name] for f in cfg.fields if f.name in was}
        # fields whose latest value is a sentinel, with its name: until a read gives another
        had = self._sentinels.get(t, {})
        sentinels = {f.name: had[f.name] for f in cfg.fields if f.name in had}
        read: dict[str, Any] = {}
        failures: list[str] = []
        good = 0
        for r in readings:
            name = r.field.name
            sentinels.pop(name, None)
            if r.value is not None:
                read[name] = values[name] = value_of(r.value)
                good += 1
                if r.value.sentinel is not None:
                    sentinels[name] = r.value.sentinel.name
                if values[name] is None:  # read, but the device gives no value (a
                    # sentinel such as SENSOR_ERROR, a NaN float): null, so not "ok"
                    failed[name] = f"no value: {name} is {r.value.text}"
                else:
                    failed.pop(name, None)
                continue
            values[name] = None
            if r.status is Status.ABSENT:
                failed.pop(name, None)
            else:
                failed[name] = f"{r.status.value}: {r.error}"
                failures.append(failed[name])
        self._values[t], self._failed[t], self._sentinels[t] = values, failed, sentinels
        # a field null for any other reason (no value this scan, or not read this scan
        # and its last read failed) is null too: never "ok" then
        failures += [e for e in failed.values() if e not in failures]
        # the first failure that says why (a "skipped" only follows an earlier one)
        error = next((e for e in failures if not e.startswith("skipped")),
                     failures[0] if failures else None)
        status = "ok" if not failures else "partial" if good else "failed"
        opts = s.options(cfg.name)
        now = self._clock()
        compared = (values, status, error, sentinels)
        if opts.publish == "on_change" and t not in self.forced \
                and self._compared.get(t) == compared \
                and now - self._sent_at.get(t, -1e18) < opts.max_silence:
            return out
        self.forced.discard(t)
        self._compared[t], self._sent_at[t] = compared, now
        own: dict[str, Any] = {"status": status, "error": error}
        if sentinels:  # in the fields' order, whichever scan read them
            own[SENTINELS] = {f.name: sentinels[f.name] for f in cfg.fields
                              if f.name in sentinels}
        state = {**values, LAST_SEEN: iso_time(last_good) if last_good is not None else None,
                 STATUS_KEY: own}
        payload = to_json(state)
        self.state[t] = payload
        out.append(Out(f"{base}/{t}", payload, s.retain))
        if opts.field_topics:
            out += [Out(f"{base}/{t}/{name}", plain(value), s.retain)
                    for name, value in read.items() if value is not None]
        return out

    def latest(self) -> list[Out]:
        """Every device's availability and latest state: after a reconnect (a broker
        restarted without persistence has forgotten them) or Home Assistant's restart."""
        base = self.settings.base
        return [Out(f"{base}/{t}/availability", a, True) for t, a in self.avail.items()] + \
            [Out(f"{base}/{t}", p, self.settings.retain) for t, p in self.state.items()]

    def offline(self) -> list[Out]:
        """A clean stop: every device offline (retained)."""
        return [Out(f"{self.settings.base}/{t}/availability", "offline", True)
                for t in self.topics.values()]

    def forget(self, t: str) -> list[Out]:
        """A device left the site: its retained messages are cleared."""
        base = self.settings.base
        out = [Out(f"{base}/{t}/availability", "", True)]
        if self.settings.retain:
            out.append(Out(f"{base}/{t}", "", True))
        for d in (self.avail, self.state, self._values, self._failed, self._sentinels,
                  self._compared, self._sent_at):
            d.pop(t, None)
        return out


def plain(value: Any) -> str:
    """A value on its own topic: numbers and names as text, flag lists as JSON."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return to_json(value)
    return str(value)
