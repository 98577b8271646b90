"""The dashboard's pure parts: trend rings (bounded, in order), ``--http`` settings and the
site file's ``http:``, the authentication check, the event hub, and the fleet's
reading of MQTT messages (fed directly: the broker side is in test_web_browser)."""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from rtupoll.config.http_settings import HttpSettings, from_options, merge, parse_listen
from rtupoll.config.site import load_site
from rtupoll.errors import ConfigError, UsageError
from rtupoll.web.trend import BYTES_PER_FIELD, POINTS, SPAN, STEP, Trend, TrendStore

if TYPE_CHECKING:
    from rtupoll.web.fleet import Fleet

# rtupoll.web.server and .fleet import aiohttp (0.2 s): the tests that need them import
# them, so an xdist worker that runs none of them does not pay for it at collection


# -- trend rings -------------------------------------------------------------------------


def test_a_ring_keeps_one_point_per_step_and_at_most_an_hour_of_steps() -> None:
    store = TrendStore(1000.0)
    t = 1000.0
    for i in range(3 * POINTS):  # three hours of readings every second
        store.add("d", "f", t + i, float(i))
    ring = store.rings[("d", "f")]
    assert len(ring) == POINTS  # bounded, whatever came
    assert ring.nbytes() == BYTES_PER_FIELD == POINTS * 8
    now = t + 3 * POINTS - 1
    got = store.series("d", "f", now)
    assert len(got["t"]) == len(got["v"]) == POINTS
    assert got["t"] == sorted(got["t"]) and got["t"][-1] == now
    assert got["t"][0] >= now - SPAN - 0.05  # the last hour, nothing older
    assert all(b - a == pytest.approx(STEP) for a, b in zip(got["t"], got["t"][1:],
                                                             strict=False))
    assert got["v"][-1] == 3 * POINTS - 1  # the newest reading of the last step


def test_points_older_than_the_span_are_not_shown_and_odd_values_are_not_kept() -> None:
    store = TrendStore(0.0)
    store.add("d", "f", 10.0, 1.5)
    store.add("d", "f", 5000.0, 2.25)
    assert store.series("d", "f", 5000.0) == {"t": [5000.0], "v": [2.25]}
    assert not store.add("d", "f", 5002.0, float("nan"))
    assert not store.add("d", "f", 5002.0, 1e39)  # beyond a float32
    assert store.series("d", "f", 5002.0)["v"] == [2.25]
    assert store.series("d", "nothing", 5000.0) == {"t": [], "v": []}


def test_values_come_back_as_the_shortest_decimal_of_their_float32() -> None:
    store = TrendStore(0.0)
    for i, v in enumerate((21.5, 0.036, 296.15, 1175.0, -3.3)):
        store.add("d", "f", 10.0 * i, v)
    assert store.series("d", "f", 40.0)["v"] == [21.5, 0.036, 296.15, 1175.0, -3.3]


def test_steps_are_wall_clock_steps_the_same_for_every_store() -> None:
    a, b = TrendStore(1001.3), TrendStore(997.7)
    for s in (a, b):
        for t in (1002.1, 1003.9, 1004.2, 1005.5):
            s.add("d", "f", t, t)
    assert a.series("d", "f", 1006.0) == b.series("d", "f", 1006.0) == {
        "t": [1003.9, 1005.5], "v": [1003.9, 1005.5]}


def test_forget_drops_the_rings_of_devices_that_left() -> None:
    store = TrendStore(0.0)
    store.add("a", "f", 1.0, 1.0)
    store.add("b", "f", 1.0, 1.0)
    store.forget({"a"})
    assert list(store.rings) == [("a", "f")]


def test_memory_per_field_is_what_the_docs_say() -> None:
    ring = Trend()
    for i in range(POINTS * 2):
        ring.add(i * 20, 1.0)
    arrays = sys.getsizeof(ring.times) + sys.getsizeof(ring.values)
    assert BYTES_PER_FIELD == 14_400
    assert BYTES_PER_FIELD <= arrays <= BYTES_PER_FIELD + 2_000  # docs/web.md: 14.4 kB


# -- settings ----------------------------------------------------------------------------


def test_listen_addresses() -> None:
    assert parse_listen("8080") == ("127.0.0.1", 8080)  # a port alone: loopback
    assert parse_listen(":8080") == ("127.0.0.1", 8080)
    assert parse_listen("0.0.0.0:80") == ("0.0.0.0", 80)
    assert parse_listen("[::1]:8080") == ("::1", 8080)
    for bad in ("host", "1.2.3.4:99999", "", "a:b"):
        with pytest.raises(UsageError):
            parse_listen(bad)


def test_loopback_open_and_guarded() -> None:
    assert HttpSettings("127.0.0.1", 1).warning() == ""
    assert HttpSettings("::1", 1).warning() == ""
    assert HttpSettings("localhost", 1).warning() == ""
    assert "readable by anyone" in HttpSettings("0.0.0.0", 1).warning()
    assert HttpSettings("0.0.0.0", 1, token="12345678").warning() == ""
    assert HttpSettings("192.168.1.5", 1, users={"a": "12345678"}).warning() == ""


def test_the_command_line_over_the_site_file() -> None:
    site = HttpSettings("0.0.0.0", 80, token="site-token", users={"u": "site-pass"})
    assert merge(None, site) is site
    cli = from_options("127.0.0.1:8080", None, ())
    assert merge(cli, site) == HttpSettings("127.0.0.1", 8080, "site-token", {"u": "site-pass"})
    only_token = from_options(None, "cli-token-1", ())
    assert merge(only_token, site) == HttpSettings("0.0.0.0", 80, "cli-token-1",
                                                   {"u": "site-pass"})
    with pytest.raises(UsageError, match="need --http HOST:PORT"):
        merge(only_token, None)
    assert from_options(None, None, ()) is None


def test_the_site_files_http_section(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    body = ("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n    devices:\n"
            "      - {profile: huiwen-aq, address: 3}\n")
    path.write_text("http: 8080\n" + body)
    assert load_site(path).http == HttpSettings("127.0.0.1", 8080)
    path.write_text("http:\n  listen: 0.0.0.0:8080\n  token: a-long-token\n"
                    "  users: {tech: correct-horse}\n" + body)
    assert load_site(path).http == HttpSettings("0.0.0.0", 8080, "a-long-token",
                                                {"tech": "correct-horse"})
    for text, line, message in (
            ("http: nowhere\n", 1, "http: 'nowhere': expected [HOST:]PORT, e.g. "
                                   "127.0.0.1:8080"),
            ("http:\n  listen: 8080\n  token: short\n", 3, "http.token: shorter than 8 "
                                                            "characters"),
            ("http:\n  listen: 8080\n  users: {tech: pw}\n", 3,
             "http.users.tech: the password is shorter than 8 characters"),
            ("http:\n  token: a-long-token\n", 2, "http: missing required key 'listen'")):
        path.write_text(text + body)
        with pytest.raises(ConfigError) as bad:
            load_site(path)
        assert str(bad.value).startswith(f"{path}:{line}: "), str(bad.value)
        assert message.split(": ", 1)[1].split("'")[0] in str(bad.value), str(bad.value)


def test_the_listeners_limits_in_the_site_file_and_on_the_command_line(tmp_path: Path
                                                                       ) -> None:
    from rtupoll.config import http_settings as hs
    assert (hs.HttpSettings("127.0.0.1", 1).header_timeout, hs.IDLE_TIMEOUT,
            hs.MAX_CONNECTIONS) == (10.0, 60.0, 256)
    path = tmp_path / "site.yaml"
    body = ("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n    devices:\n"
            "      - {profile: huiwen-aq, address: 3}\n")
    path.write_text("http:\n  listen: 8080\n  header_timeout: 2.5\n  idle_timeout: 30\n"
                    "  max_connections: 40\n  hosts: [Dash.Example, '[::1]', 10.0.0.1]\n" + body)
    site = load_site(path).http
    assert site is not None
    assert (site.header_timeout, site.idle_timeout, site.max_connections, site.hosts) == (
        2.5, 30.0, 40, ("dash.example", "::1", "10.0.0.1"))
    # the command line's, where given, over the file's
    cli = from_options(None, None, (), {"idle_timeout": 5.0, "max_connections": None,
                                         "hosts": ()})
    got = merge(cli, site)
    assert got is not None
    assert (got.header_timeout, got.idle_timeout, got.max_connections, got.hosts) == (
        2.5, 5.0, 40, ("dash.example", "::1", "10.0.0.1"))
    for text, message in (("header_timeout: 0", "0 is not a number of seconds"),
                          ("idle_timeout: 4000", "4000 is not a number of seconds"),
                          ("max_connections: 1.5", "expected a whole number"),
                          ("hosts: [a b]", "'a b' is not a host name")):
        path.write_text(f"http:\n  listen: 8080\n  {text}\n" + body)
        with pytest.raises(ConfigError, match=message) as bad:
            load_site(path)
        assert str(bad.value).startswith(f"{path}:3: "), str(bad.value)


def test_the_host_names_a_loopback_listener_answers_to() -> None:
    s = HttpSettings("127.0.0.1", 8080, hosts=("dash.example",))
    for ok in ("localhost", "LOCALHOST.", "app.localhost", "127.0.0.1", "127.1.2.3", "[::1]",
               "::1", "dash.example"):
        assert s.allows_host(ok), ok
    for foreign in ("evil.com", "localhost.evil.com", "10.0.0.1", "", "dash.example.evil",
                    "127.0.0.1.nip.io"):
        assert not s.allows_host(foreign), foreign


# -- authentication ----------------------------------------------------------------------


def test_authorised() -> None:
    from rtupoll.web.server import COOKIE, authorised, cookie_value
    s = HttpSettings("0.0.0.0", 1, token="the-token-1", users={"tech": "correct-horse"})
    none: dict[str, str] = {}

    def basic(text: str) -> dict[str, str]:
        return {"Authorization": "Basic " + base64.b64encode(text.encode()).decode()}

    assert authorised(HttpSettings("0.0.0.0", 1), none, none, none)  # open
    assert not authorised(s, none, none, none)
    assert authorised(s, {"Authorization": "Bearer the-token-1"}, none, none)
    assert authorised(s, {"Authorization": "bearer  the-token-1"}, none, none)
    assert not authorised(s, {"Authorization": "Bearer the-token-2"}, none, none)
    assert authorised(s, none, {COOKIE: cookie_value("the-token-1")}, none)
    assert not authorised(s, none, {COOKIE: "the-token-1"}, none)  # the token is no cookie
    assert authorised(s, none, none, {"token": "the-token-1"})
    assert authorised(s, basic("tech:correct-horse"), none, none)
    assert not authorised(s, basic("tech:correct-horsE"), none, none)
    assert not authorised(s, basic("nobody:correct-horse"), none, none)
    # bytes that are not ASCII (aiohttp keeps undecodable ones as surrogates): refused,
    # never an error
    for bad in ("Bearer th\udcffe-token", "Basic \udcff\udcfe", "Basic t\u00e9st",
                "Basic " + base64.b64encode(b"tech:\xff").decode()):
        assert not authorised(s, {"Authorization": bad}, none, none), bad
    assert not authorised(s, none, {COOKIE: "\udcff"}, {"token": "\u00e9\udcff"})
    assert not authorised(s, {"Authorization": "Basic %%%"}, none, none)
    assert not authorised(s, {"Authorization": "Basic " + base64.b64encode(b"\xff").decode()},
                          none, none)


def test_the_hub_makes_each_event_once_and_gives_every_stream_the_same_bytes() -> None:
    from rtupoll.web.server import Hub
    async def run() -> None:
        hub = Hub()
        calls: list[int] = []

        def data() -> str:
            calls.append(1)
            return "2"

        hub.publish("d:a", "device", data)  # nobody listens: never made
        assert hub.pending == {}
        one = hub.join()
        two = hub.join()
        assert hub.epoch == 2  # a snapshot per client: the next device events are whole
        hub.publish("d:a", "device", "1")
        hub.publish("d:b", "device", "x")
        hub.publish("d:a", "device", data)  # the latest of a key, in its first place
        assert calls == [] and not one.wake.is_set()  # nothing until the flush
        hub.flush()  # what the timer does BATCH seconds after the first publish
        assert one.wake.is_set() and two.wake.is_set() and calls == [1]
        expected = b"event: device\ndata: 2\n\nevent: device\ndata: x\n\n"
        assert one.take() == expected and two.take() == expected
        assert not one.wake.is_set() and one.take() == b""
        hub.close()

    asyncio.run(run())


def test_a_stream_that_stops_reading_gets_a_snapshot_not_a_backlog() -> None:
    from rtupoll.web.server import BEHIND, Hub
    async def run() -> None:
        hub = Hub()
        slow, live = hub.join(), hub.join()
        chunk = "x" * 100_000
        for _ in range(BEHIND // len(chunk) + 2):
            hub.publish("d:a", "device", chunk)
            hub.flush()
            live.take()  # this one reads
        assert slow.behind and not slow.queue and slow.wake.is_set()
        assert not live.behind
        hub.publish("d:a", "device", "y")
        hub.flush()
        assert not slow.queue and live.take() == b"event: device\ndata: y\n\n"
        epoch = hub.epoch
        hub.rejoin(slow)
        assert not slow.behind and hub.epoch == epoch + 1
        hub.publish("d:a", "device", "z")
        hub.flush()
        assert slow.take() == live.take() == b"event: device\ndata: z\n\n"
        hub.close()

    asyncio.run(run())


def test_what_waits_for_all_the_slow_streams_is_bounded_together() -> None:
    """Each of 20 streams reads a little (never BEHIND): together they never hold more
    than BUDGET bytes; the furthest behind start afresh. A take is at most CHUNK bytes
    (or one event), so a slow reader's backlog stays in the hub, counted."""
    from rtupoll.web.server import BEHIND, BUDGET, CHUNK, Hub
    async def run() -> None:
        hub = Hub()
        streams = [hub.join() for _ in range(20)]
        chunk = "x" * 100_000
        most = 0
        for i in range(400):
            hub.publish("d:a", "device", chunk)
            hub.flush()
            for s in streams[:i % 20]:  # each reads now and then
                got = s.take()
                assert len(got) <= max(CHUNK, len(chunk) + 30)
            most = max(most, sum(s.size for s in hub.clients))
        assert most <= BUDGET < 20 * BEHIND
        assert any(s.behind for s in streams)  # dropped, a snapshot next
        hub.close()

    asyncio.run(run())


# -- the fleet ---------------------------------------------------------------------------

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
