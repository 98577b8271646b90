"""The fleet's reading of MQTT messages, fed directly (the broker side is in
test_web_browser) (rtupoll.web.fleet)."""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from rtupoll.web.fleet import Fleet

# rtupoll.web.server and .fleet import aiohttp (0.2 s): the tests that need them import
# them, so an xdist worker that runs none of them does not pay for it at collection


INFO = {"gateway": "a", "version": "0.1.0", "base": "rtupoll/a", "devices": {
    "huiwen-aq@3": {"profile": "huiwen-aq", "address": 3, "bus": "line1", "fields": {
        "co2": {"label": "CO2", "unit": "ppm", "kind": "number", "precision": 0},
        "co2_level": {"label": "CO2 level", "unit": "", "kind": "enum", "precision": None},
        "alarms": {"label": "alarms", "unit": "", "kind": "flags", "precision": None},
        "temperature": {"label": "temperature", "unit": "°C", "kind": "number",
                        "precision": 1}}}}}


def feed(fleet: Fleet, topic: str, payload: Any) -> bool:
    """One message, handled as ``rtupoll web`` handles it; False: dropped."""
    return fleet.handle(topic, (payload if isinstance(payload, str) else json.dumps(payload))
                        .encode())


def test_the_fleet_reads_a_gateways_topics() -> None:
    from rtupoll.web.fleet import Fleet
    now = [1_800_000_000.0]
    fleet = Fleet("rtupoll", "mqtt://broker:1883/rtupoll", clock=lambda: now[0])
    # state before the gateway's bridge/info: held, then placed when the info comes
    feed(fleet, "rtupoll/a/huiwen-aq_3", {"co2": 612, "co2_level": "GOOD", "alarms": [],
                                          "temperature": 21.5,
                                          "last_seen": "2027-01-15T08:00:00.000Z",
                                          "_rtupoll": {"status": "ok"}})
    feed(fleet, "rtupoll/a/huiwen-aq_3/availability", "online")
    assert fleet.snapshot()["gateways"] == []
    feed(fleet, "rtupoll/a/bridge/info", INFO)
    feed(fleet, "rtupoll/a/bridge/state", "online")
    snap = fleet.snapshot()
    assert snap["mode"] == "fleet" and snap["title"] == "mqtt://broker:1883/rtupoll"
    (gw,) = snap["gateways"]
    assert (gw["id"], gw["base"], gw["version"], gw["online"]) == ("a", "rtupoll/a", "0.1.0",
                                                                   True)
    (bus,) = gw["buses"]
    (dev,) = bus["devices"]
    assert bus["name"] == "line1"
    assert (dev["key"], dev["state"], dev["address"]) == ("rtupoll/a/huiwen-aq_3", "online", 3)
    fields = {f["name"]: f for f in dev["fields"]}
    assert (fields["co2"]["text"], fields["co2"]["unit"], fields["co2"]["label"]) == (
        "612", "ppm", "CO2")
    assert fields["temperature"]["text"] == "21.5"
    assert fields["co2_level"]["badges"] == [{"name": "GOOD", "severity": "info"}]
    assert fields["alarms"]["badges"] == [] and fields["alarms"]["text"] == "none"
    # a trend point at the reading's own time (last_seen), from the state message
    now[0] += 30
    assert fleet.trend("rtupoll/a/huiwen-aq_3", "co2") == {"t": [1_800_000_000.0],
                                                            "v": [612.0]}
    # a failed field: no value, the gateway's own error
    feed(fleet, "rtupoll/a/huiwen-aq_3", {"co2": None, "co2_level": "GOOD", "alarms": ["fan"],
                                          "temperature": 21.5,
                                          "_rtupoll": {"status": "partial",
                                                       "error": "timeout: no reply"}})
    dev = fleet.snapshot()["gateways"][0]["buses"][0]["devices"][0]
    fields = {f["name"]: f for f in dev["fields"]}
    assert fields["co2"]["value"] is None and fields["co2"]["status"] == "failed"
    assert fields["co2"]["error"] == "timeout: no reply"
    assert fields["alarms"]["badges"] == [{"name": "fan", "severity": "info"}]
    # the gateway's last will: offline; devices that went away
    feed(fleet, "rtupoll/a/bridge/state", "offline")
    feed(fleet, "rtupoll/a/huiwen-aq_3/availability", "offline")
    gw = fleet.snapshot()["gateways"][0]
    assert not gw["online"] and gw["buses"][0]["devices"][0]["state"] == "offline"
    # its retained values are shown as what they are: the last ones, with their time
    co2_level = gw["buses"][0]["devices"][0]["fields"][1]
    assert co2_level["value"] is None and co2_level["status"] == "offline"
    assert co2_level["last"]["text"] == "GOOD"
    # removed for good: an empty retained info
    fleet.on_message("rtupoll/a/bridge/info", b"")
    assert fleet.snapshot()["gateways"] == []


def test_two_gateways_and_their_devices_never_mix() -> None:
    from rtupoll.web.fleet import Fleet
    fleet = Fleet("rtupoll")
    for gw in ("a", "b"):
        feed(fleet, f"rtupoll/{gw}/bridge/info", {**INFO, "gateway": gw,
                                                  "base": f"rtupoll/{gw}"})
        feed(fleet, f"rtupoll/{gw}/huiwen-aq_3", {"co2": 600 if gw == "a" else 1400})
    keys = {d["key"]: d for g in fleet.snapshot()["gateways"] for b in g["buses"]
            for d in b["devices"]}
    assert set(keys) == {"rtupoll/a/huiwen-aq_3", "rtupoll/b/huiwen-aq_3"}
    assert keys["rtupoll/b/huiwen-aq_3"]["fields"][0]["value"] == 1400


def test_what_the_fleet_ignores() -> None:
    from rtupoll.web.fleet import MAX_WAITING, Fleet
    fleet = Fleet("rtupoll")
    feed(fleet, "rtupoll/a/bridge/info", "not json")
    feed(fleet, "rtupoll/b/bridge/info", [1, 2])
    assert fleet.snapshot()["gateways"] == []
    feed(fleet, "rtupoll/a/bridge/info", INFO)
    feed(fleet, "rtupoll/a/huiwen-aq_3", "garbage{")
    feed(fleet, "rtupoll/a/huiwen-aq_3", [1])
    feed(fleet, "rtupoll/a/nobody", {"co2": 1})
    feed(fleet, "rtupoll/a/huiwen-aq_3/co2", "5")  # a field topic
    dev = fleet.snapshot()["gateways"][0]["buses"][0]["devices"][0]
    assert dev["state"] == "starting" and all(f["status"] == "waiting" for f in dev["fields"])
    for i in range(MAX_WAITING + 10):  # topics of gateways never seen: bounded
        fleet.on_message(f"elsewhere/{i}", b"x")
    assert len(fleet.waiting) == MAX_WAITING


def test_a_bad_message_is_dropped_on_its_own(caplog: pytest.LogCaptureFixture) -> None:
    from rtupoll.web.fleet import Fleet
    fleet = Fleet("rtupoll", "mqtt://broker:1883/rtupoll")
    assert feed(fleet, "rtupoll/a/bridge/info", INFO)
    huge = "9" * 400
    with caplog.at_level(logging.WARNING, "rtupoll.web"):
        # a 400-digit number (float() of it: OverflowError), bad JSON, wrong types, an
        # integer too long for Python's parser, nesting too deep
        assert feed(fleet, "rtupoll/c/bridge/info", '{"devices": {"x": {"fields": {"v": '
                    f'{{"precision": {huge}}}}}, "address": {huge}}}}}, "gateway": {huge}}}')
        assert feed(fleet, "rtupoll/a/huiwen-aq_3", f'{{"co2": {huge}, "temperature": 1e999}}')
        assert not feed(fleet, "rtupoll/a/huiwen-aq_3", "{not json")
        assert not feed(fleet, "rtupoll/a/huiwen-aq_3", "9" * 5000)
        assert not feed(fleet, "rtupoll/a/huiwen-aq_3", "[" * 100_000)
        assert not feed(fleet, "rtupoll/a/bridge/info", '{"devices": []}')
        assert not feed(fleet, "rtupoll/b/bridge/info", b"\xff\xfe".decode("latin-1"))
        assert feed(fleet, "rtupoll/a/huiwen-aq_3", {"co2": {"a": [1]}, "temperature": "hot",
                                                     "co2_level": 5, "alarms": "fan"})
        # and the next good message is shown
        assert feed(fleet, "rtupoll/a/huiwen-aq_3", {"co2": 640, "temperature": 22.5})
    (gw,) = (g for g in fleet.snapshot()["gateways"] if g["id"] == "a")
    dev = gw["buses"][0]["devices"][0]
    assert {f["name"]: f["text"] for f in dev["fields"]}["co2"] == "640"
    # one line for the first, the rest counted in the next line a minute later
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and lines[0].startswith("--mqtt mqtt://broker:1883/rtupoll: "
                                                   "dropped 1 message: 1 ")
    assert all(r.exc_info is None for r in caplog.records)
    assert fleet.dropped.total >= 5


def test_device_keys_are_their_state_topics_unique_by_construction() -> None:
    from rtupoll.web.fleet import Fleet
    fleet = Fleet("rtupoll")
    one = {"profile": "p", "address": 1, "bus": "b", "fields": {
        "temperature": {"label": "T", "unit": "°C", "kind": "number", "precision": 1}}}
    # device "x/y" of the gateway at rtupoll/site, device "y" of the one at rtupoll/site/x
    feed(fleet, "rtupoll/site/bridge/info", {"gateway": "site", "devices": {
        "x_y": {**one, "name": "x/y"}}})
    feed(fleet, "rtupoll/site/x/bridge/info", {"gateway": "x", "devices": {
        "y": {**one, "name": "y"}}})
    feed(fleet, "rtupoll/site/x_y", {"temperature": 23.5})
    feed(fleet, "rtupoll/site/x/y", {"temperature": 88.8})
    shown = {d["key"]: (d["name"], d["fields"][0]["text"])
             for g in fleet.snapshot()["gateways"] for b in g["buses"] for d in b["devices"]}
    assert shown == {"rtupoll/site/x_y": ("x/y", "23.5"), "rtupoll/site/x/y": ("y", "88.8")}
    assert fleet.trend("rtupoll/site/x_y", "temperature")["v"] == [23.5]
    assert fleet.trend("rtupoll/site/x/y", "temperature")["v"] == [pytest.approx(88.8, 1e-6)]


def test_every_size_in_the_fleet_is_bounded() -> None:
    from rtupoll.web import fleet as f
    fleet = f.Fleet("rtupoll")
    # precision: at most MAX_PRECISION decimals, whatever bridge/info says
    info = {"gateway": "a", "devices": {"d": {"fields": {
        "v": {"label": "v", "kind": "number", "precision": 100_000_000},
        "w": {"label": "w" * 10_000, "kind": "number", "precision": -5}}}}}
    feed(fleet, "rtupoll/a/bridge/info", info)
    feed(fleet, "rtupoll/a/d", {"v": 1.5, "w": 2.25, "junk": "x" * 100_000})
    state = json.dumps(fleet.snapshot())
    assert len(state) < 2_000
    fields = fleet.snapshot()["gateways"][0]["buses"][0]["devices"][0]["fields"]
    assert [x["text"] for x in fields] == ["1.500000", "2"]
    assert len(fields[1]["label"]) == f.MAX_TEXT
    # fields per gateway
    many = {"gateway": "b", "devices": {f"d{i}": {"fields": {
        f"x{j}": {"kind": "number"} for j in range(100)}} for i in range(50)}}
    feed(fleet, "rtupoll/b/bridge/info", many)
    shown = sum(len(d["fields"]) for g in fleet.snapshot()["gateways"] if g["id"] == "b"
                for b in g["buses"] for d in b["devices"])
    assert shown == f.MAX_FIELDS
    # messages of unknown gateways: bounded in bytes, not only in count
    for i in range(100):
        fleet.handle(f"elsewhere/{i}", b"x" * 500_000)
    assert fleet.waiting_bytes <= f.MAX_WAITING_BYTES
    assert sum(len(t) + len(p) for t, p in fleet.waiting.items()) == fleet.waiting_bytes
    assert not fleet.handle("elsewhere/big", b"x" * (f.MAX_MESSAGE + 1))
    # gateways
    for i in range(f.MAX_GATEWAYS + 5):
        fleet.handle(f"rtupoll/g{i}/bridge/info", json.dumps({"devices": {}}).encode())
    assert len(fleet.gateways) == f.MAX_GATEWAYS


def test_the_fleet_shows_kelvin_as_celsius_as_a_polling_process_does() -> None:
    """A gateway publishes its device's unit (the IRNET's K, bridge/info says so); the
    fleet's page shows it as every screen does (``model.interpret.shown_number``)."""
    from rtupoll.web.fleet import field_json, shown_value
    meta = {"label": "Sensor temperature", "unit": "K", "kind": "number", "precision": 2}
    got = field_json("temperature", meta, {"temperature": 296.67}, 1.8e9, "")
    assert (got["value"], got["text"], got["unit"]) == (23.52, "23.52", "°C")
    offset = {**meta, "label": "Temperature offset"}  # a difference moves by no 273.15
    assert shown_value("temperature_offset", offset, 1.5) == 1.5
    assert shown_value("co2", {"unit": "ppm"}, 612) == 612


def test_a_gateways_trends_outlive_its_info_again_but_not_its_devices() -> None:
    from rtupoll.web.fleet import Fleet
    now = [1_800_000_000.0]
    fleet = Fleet("rtupoll", clock=lambda: now[0])
    one = {"fields": {"t": {"kind": "number", "precision": 1}}}
    feed(fleet, "rtupoll/site/bridge/info", {"devices": {"a": one, "b": one}})
    feed(fleet, "rtupoll/site/x/bridge/info", {"devices": {"y": one}})
    for topic in ("rtupoll/site/a", "rtupoll/site/b", "rtupoll/site/x/y"):
        feed(fleet, topic, {"t": 1.5})
    now[0] += 10
    feed(fleet, "rtupoll/site/bridge/info", {"devices": {"a": one}})  # again, without b
    assert fleet.trend("rtupoll/site/a", "t")["v"] == [1.5]
    assert fleet.trend("rtupoll/site/b", "t")["v"] == []
    assert fleet.fields == 2
    feed(fleet, "rtupoll/site/bridge/info", "")  # gone for good: not the one under it
    assert fleet.trend("rtupoll/site/a", "t")["v"] == []
    assert fleet.trend("rtupoll/site/x/y", "t")["v"] == [1.5]
    assert fleet.fields == 1


def test_the_fleet_colours_readings_by_the_severities_bridge_info_carries(
        caplog: pytest.LogCaptureFixture) -> None:
    """Each name's severity as ``bridge/info`` says, ``unlisted`` for one it does not
    list; a gateway that sends none gets neutral badges; what is not a severity, or
    past the limits, is left out (and counted)."""
    from rtupoll.web.fleet import MAX_NAMES, Fleet
    fleet = Fleet("rtupoll", "mqtt://broker:1883/rtupoll")
    device: dict[str, Any] = INFO["devices"]["huiwen-aq@3"]  # type: ignore[index]
    fields = device["fields"]
    level = {**fields["co2_level"], "unlisted": "warning", "severities": {
        "GOOD": "ok", "POOR": "error", "MILD": "purple"}}
    alarms = {**fields["alarms"], "unlisted": "warning", "severities": {
        "fan": "info", "door": "error", "lamp": "ok"}}
    many = {**fields["alarms"], "unlisted": "warning",
            "severities": {f"f{i}": "error" for i in range(MAX_NAMES + 1)}}
    info = {**INFO, "devices": {"huiwen-aq@3": {**device, "fields": {
        "co2_level": level, "alarms": alarms, "many": many, "old": fields["alarms"]}}}}
    with caplog.at_level(logging.WARNING, "rtupoll.web"):
        assert feed(fleet, "rtupoll/a/bridge/info", info)

    def shown(state: dict[str, Any]) -> dict[str, Any]:
        assert feed(fleet, "rtupoll/a/huiwen-aq_3", state)
        dev = fleet.snapshot()["gateways"][0]["buses"][0]["devices"][0]
        return {f["name"]: (f["severity"], [(b["name"], b["severity"]) for b in f["badges"]])
                for f in dev["fields"]}

    got = shown({"co2_level": "POOR", "alarms": ["fan", "lamp"], "many": ["f1"],
                 "old": ["fan"]})
    assert got == {"co2_level": ("error", [("POOR", "error")]),
                   "alarms": ("info", [("fan", "info"), ("lamp", "ok")]),
                   "many": ("ok", [("f1", "info")]),  # past MAX_NAMES: none, neutral
                   "old": ("ok", [("fan", "info")])}  # an older gateway's: neutral
    got = shown({"co2_level": "MILD", "alarms": ["door", "bit 3"], "many": [], "old": []})
    assert got["co2_level"] == ("warning", [("MILD", "warning")])  # "purple": unlisted
    assert got["alarms"] == ("error", [("door", "error"), ("bit 3", "warning")])
    assert shown({"co2_level": "unknown (9)", "alarms": [], "many": [], "old": []})[
        "co2_level"] == ("warning", [("unknown (9)", "warning")])
    assert "severities past the limits" in caplog.text


def test_a_sentinel_is_shown_by_the_name_the_state_message_gives_it() -> None:
    """A null value that ``_rtupoll.sentinels`` names is that name, a badge of the
    severity ``bridge/info`` gives it (neutral for a name it does not list); a null
    without one (an older gateway's, a failed read) is no reading, and what is not a
    field's sentinel's name is left out, never an error."""
    from rtupoll.web.fleet import MAX_TEXT, Fleet
    fleet = Fleet("rtupoll")
    sensor = {"label": "Temperature 1", "unit": "°C", "kind": "number", "precision": 1,
              "sentinels": {"NO_SENSOR": "error", "OVERFLOW": "magenta"}}
    plain = {"label": "Temperature 2", "unit": "°C", "kind": "number", "precision": 1}
    feed(fleet, "rtupoll/a/bridge/info", {"gateway": "a", "devices": {"t": {"fields": {
        "t1": sensor, "t2": plain, "t3": plain}}}})

    def shown(state: dict[str, Any]) -> dict[str, tuple[str, str, str, list[Any]]]:
        assert feed(fleet, "rtupoll/a/t", state)
        dev = fleet.snapshot()["gateways"][0]["buses"][0]["devices"][0]
        return {f["name"]: (f["status"], f["text"], f["severity"],
                            [(b["name"], b["severity"]) for b in f["badges"]])
                for f in dev["fields"]}

    got = shown({"t1": None, "t2": None, "t3": 21.5, "_rtupoll": {
        "status": "partial", "error": "no value: t1 is NO_SENSOR",
        "sentinels": {"t1": "NO_SENSOR", "t2": "NOT_AVAILABLE", "nope": "X"}}})
    assert got == {"t1": ("ok", "NO_SENSOR", "error", [("NO_SENSOR", "error")]),
                   "t2": ("ok", "NOT_AVAILABLE", "info", [("NOT_AVAILABLE", "info")]),
                   "t3": ("ok", "21.5", "ok", [])}
    assert shown({"t1": None, "t2": 20.0, "t3": 21.5, "_rtupoll": {
        "status": "partial", "sentinels": {"t1": "OVERFLOW"}}})["t1"] == (
        "ok", "OVERFLOW", "info", [("OVERFLOW", "info")])  # "magenta": no severity
    # an older gateway's message, and sentinels that are not names: no reading
    for own in ({"status": "partial"}, {"sentinels": ["t1"]}, {"sentinels": {"t1": 7}},
                {"sentinels": {"t1": None}}, "partial"):
        assert shown({"t1": None, "t2": 20.0, "t3": 21.5, "_rtupoll": own})["t1"][:2] == (
            "failed", "no reading"), own
    # a value is never hidden behind a sentinel's name; a long name is cut short
    assert shown({"t1": 19.5, "t2": 20.0, "t3": 21.5, "_rtupoll": {
        "sentinels": {"t1": "NO_SENSOR"}}})["t1"][:2] == ("ok", "19.5")
    long = shown({"t1": None, "t2": 20.0, "t3": 21.5, "_rtupoll": {
        "sentinels": {"t1": "N" * 10_000}}})["t1"]
    assert len(long[1]) == MAX_TEXT and long[2] == "info"
