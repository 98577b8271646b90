"""The dashboard of a polling process (``web.state``) and the fleet page (``web.fleet``,
from what a gateway publishes) show one field alike: its label, unit, kind and
precision come from one home (``model.interpret.field_kind``/``shown_precision``,
``Field.title``), and so do its value and text, and its severity and its badges'
(``model.interpret.reading_severity``, the fleet page's from the names' severities
``bridge/info`` carries), a sentinel's name and severity too (the state message names
it, ``bridge/info`` gives its severity); and both name the gateway by the one host-name rule MQTT
publishes under (``config.mqtt_settings.default_gateway_id``)."""

from __future__ import annotations

import dataclasses
import json
import socket
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from rtupoll.config.http_settings import HttpSettings
from rtupoll.config.library import load_library
from rtupoll.config.mqtt_settings import MqttSettings, default_gateway_id, parse_url
from rtupoll.config.site import from_specs
from rtupoll.jobs.stats import Reading
from rtupoll.model.codec import encode_raw
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Field, Profile
from rtupoll.outputs.fleet import bridge_info
from rtupoll.outputs.mqtt_state import StatePublisher
from rtupoll.web.fleet import Fleet
from rtupoll.web.service import WebService
from rtupoll.web.state import field_state

SHOWN = ("label", "unit", "kind", "precision", "value", "text", "status", "severity",
         "badges")


def last(raw: int) -> Callable[[Field], tuple[int, ...]]:
    """A field's registers: ``raw`` in its last, 0 in the others."""
    return lambda f: (0,) * (f.words - 1) + (raw,)


def pages(profile: Profile, fields: tuple[Field, ...], words: Callable[[Field], tuple[int, ...]]
          ) -> Iterator[tuple[Field, dict[str, Any], dict[str, Any]]]:
    """Each of ``fields`` of a device of ``profile`` holding the registers ``words(field)``:
    the dashboard's field and the fleet page's, made from the gateway's ``bridge/info``
    and state message (``outputs.mqtt_state``'s) as a broker carries them."""
    site = from_specs("/dev/null", [(profile.id, 1)])
    bus = site.buses[0]
    dev = dataclasses.replace(bus.devices[0], fields=fields)
    fleet = Fleet("rtupoll", clock=lambda: 1.8e9)
    info = bridge_info("gw", "rtupoll/gw", [(bus, dev)], {dev.name: "dev"}, "1")
    assert fleet.handle("rtupoll/gw/bridge/info", json.dumps(info).encode())
    dashboard: dict[str, dict[str, Any]] = {}
    readings = []
    for f in dev.fields:
        r = Reading(1.8e9, dev, f, interpret(f, words(f)))
        dashboard[f.name] = field_state(f, r, None)
        readings.append(r)
    (state,) = [o for o in StatePublisher(parse_url("mqtt://b/rtupoll/gw"), {dev.name: "dev"})
                .readings(dev, True, 1.8e9, readings) if o.topic == "rtupoll/gw/dev"]
    assert fleet.handle(state.topic, state.payload.encode())
    (gw,) = fleet.snapshot()["gateways"]
    ((shown,),) = [b["devices"] for b in gw["buses"]]
    page = {f["name"]: f for f in shown["fields"]}
    assert list(page) == [f.name for f in dev.fields], profile.id
    for f in dev.fields:
        yield f, {k: dashboard[f.name].get(k) for k in SHOWN}, \
            {k: page[f.name].get(k) for k in SHOWN}


def test_the_dashboard_and_the_fleet_page_show_every_bundled_field_alike() -> None:
    """Every field of every bundled profile, holding a raw 7 in its last register, is
    shown alike, severity and badges too."""
    compared, told = 0, 0
    kinds: set[str] = set()
    severity: Counter[str] = Counter()
    for profile in load_library().profiles.values():
        for f, ours, theirs in pages(profile, profile.fields, last(7)):
            assert ours == theirs, (profile.id, f.name)
            compared += 1
            kinds.add(ours["kind"])
            told += ours["precision"] is not None
            if ours["kind"] in ("enum", "flags"):
                severity[ours["severity"]] += 1
    assert compared > 1000 and kinds == {"number", "enum", "flags", "text"}
    assert told > 500  # scaled registers are told their decimals on both pages
    # enum codes and flags of every severity, not the neutral "info" of no severities
    assert severity["warning"] > 50 and severity["error"] > 5 and severity["ok"] > 10, severity


def test_every_enum_value_and_flag_has_the_dashboards_severity_on_the_fleet_page() -> None:
    """Every enum code and flag of every bundled profile, an undocumented code or bit,
    and none set: the fleet page's severity and badges are the dashboard's."""
    seen: Counter[str] = Counter()
    for profile in load_library().profiles.values():
        fields = tuple(f for f in profile.fields if f.enum or f.flags)
        if not fields:
            continue
        raws: set[int] = {0, 1 << 15 | 1 << 14}  # none set, and undocumented bits or codes
        for f in fields:
            raws |= {c for c in (*f.enum, *f.flags) if 0 <= c < 1 << 16}
            raws.add(sum(m for m in f.flags if 0 <= m < 1 << 16))  # every flag at once
        for raw in sorted(raws):
            for f, ours, theirs in pages(profile, fields, last(raw)):
                assert ours == theirs, (profile.id, f.name, raw)
                seen[ours["severity"]] += 1
                seen.update(b["severity"] for b in ours["badges"])
    assert seen["ok"] and seen["info"] and seen["warning"] and seen["error"], seen


def test_every_sentinel_has_the_dashboards_name_and_severity_on_the_fleet_page() -> None:
    """Every sentinel of every bundled profile ("not available", "overflow", "no
    sensor"): the fleet page shows its name, a badge of its severity, as the dashboard
    does, where it had only "no reading"."""
    seen: Counter[str] = Counter()
    for profile in load_library().profiles.values():
        fields = tuple(f for f in profile.fields if f.sentinels)
        for i in range(max((len(f.sentinels) for f in fields), default=0)):
            def sentinel(f: Field, i: int = i) -> tuple[int, ...]:  # its i-th, or last
                stored = list(f.sentinels)[min(i, len(f.sentinels) - 1)]
                return encode_raw(stored, f.layout)

            for f, ours, theirs in pages(profile, fields, sentinel):
                assert ours == theirs, (profile.id, f.name)
                name = ours["text"]
                assert name in {c.name for c in f.sentinels.values()}, (profile.id, f.name)
                assert ours["badges"] == [{"name": name, "severity": ours["severity"]}]
                seen[ours["severity"]] += 1
    assert seen["info"] > 10 and seen["warning"] > 10 and seen["error"] >= 8, seen


AWKWARD = ["pi_lab-01", "Pi-Lab-01", "pi.lab 01", "PUMP-HOUSE.example.com", "-edge-",
           "__x__", "Übergabe-1", "###", "", "a" * 80, " spaced \t"]


@pytest.mark.parametrize("host", AWKWARD)
def test_the_dashboard_names_the_gateway_as_mqtt_does(host: str,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The host name is the one input: the dashboard's gateway id (``poll --http``) is
    the id the gateway publishes under, which the fleet page shows."""
    monkeypatch.setattr(socket, "gethostname", lambda: host)
    published = MqttSettings(host="broker").gateway_id
    assert published == default_gateway_id(host)
    assert WebService(HttpSettings("127.0.0.1", 0)).gateway == published
