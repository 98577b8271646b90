"""The dashboard in a real browser: the distribution's headless chromium, driven by
selenium, against ``rtupoll poll --http`` polling the simulator, and ``rtupoll web``
reading a real mosquitto. What is checked is what the page shows (the DOM as
rendered), and that the browser's console has no errors.

The page's colours follow the system's scheme (light and dark, checked in the page's
computed style). Screenshots (light, dark, phone width) are taken with
``RTUPOLL_DOCS_SCREENSHOTS=1``: into the test's directory, and those docs/web.md shows
into docs/ (each set cost the browser about 0.9 CPU-s: not on every run).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from rtupoll.sim.faults import FaultSet, parse_fault
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.web_helpers import (
    Events,
    chromium,
    color_scheme,
    console_errors,
    devices,
    gateway_and_fleet,
    get_json,
    have_chromium,
    phone,
    repainted,
    running,
    until,
)

pytestmark = pytest.mark.skipif(not have_chromium(), reason="chromium and chromedriver "
                                "(Debian: chromium, chromium-driver) are not installed")
DOCS = Path(__file__).resolve().parents[2] / "docs"
IN_DOCS = {"web.png", "web-phone-dark.png", "web-fleet.png"}  # docs/web.md shows these
DEMO = ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "banner-ez-array@5",
        "co2meter-an117@4"]

# what the page shows, read from the DOM
SHOWN = """
return Array.from(document.querySelectorAll('.device')).map(c => ({
  key: c.dataset.key, state: c.dataset.state, down: c.classList.contains('down'),
  badge: c.querySelector('.state').textContent,
  gateway: c.closest('.gateway').dataset.gateway,
  gatewayDown: c.closest('.gateway').classList.contains('down'),
  health: c.querySelector('.health').textContent,
  fields: Array.from(c.querySelectorAll('tr.field')).map(r =>
    [r.dataset.field, r.querySelector('td.val').textContent]),
  badges: Array.from(c.querySelectorAll('tr.field')).map(r =>
    [r.dataset.field, Array.from(r.querySelectorAll('.badge')).map(b =>
      b.textContent + ':' + b.className)])}));
"""


# an open chart, read at once (it is redrawn with every reading)
CHART = """
const svg = document.querySelector('.device[data-key="' + arguments[0] + '"] svg.trend');
if (!svg) return null;
const line = svg.querySelector('polyline');
return {points: Number(svg.dataset.points),
        ys: line ? line.getAttribute('points').split(' ').map(p => Number(p.split(',')[1])) : [],
        note: svg.parentNode.querySelector('.chart-note').textContent};
"""


def chart(driver: Any, key: str) -> dict[str, Any] | None:
    got: dict[str, Any] | None = driver.execute_script(CHART, key)
    return got


def click_chart(driver: Any, key: str, name: str, *, opened: bool) -> None:
    """Click a field's row until its chart is open (or closed). A click the page handles
    opens or closes the chart at once (in the click's own handler); one that missed (the
    cards are laid out anew as readings come: the row can move, or be drawn anew, between
    selenium finding it and clicking it, seen on a loaded machine) changed nothing, and
    the row is clicked again."""
    from selenium.common.exceptions import (
        ElementClickInterceptedException,
        StaleElementReferenceException,
    )

    row = f'.device[data-key="{key}"] tr[data-field="{name}"]'

    def done() -> bool:
        with contextlib.suppress(StaleElementReferenceException,
                                 ElementClickInterceptedException):
            driver.find_element("css selector", row).click()
        return bool(driver.find_elements(
            "css selector", f'.device[data-key="{key}"] svg.trend')) is opened

    until(done, f"the chart of {key} {name} {'open' if opened else 'closed'}")


def shown(driver: Any) -> dict[str, dict[str, Any]]:
    out = {}
    for d in driver.execute_script(SHOWN):  # fields as pairs: in the page's order
        d["fields"], d["badges"] = dict(d["fields"]), dict(d["badges"])
        out[d["key"]] = d
    return out


@pytest.fixture(scope="module")
def one_chromium() -> Iterator[Any]:
    """One headless chromium for the tests of this module (starting one is ~1 CPU-s);
    each test's server is another origin, so no page sees another's storage."""
    with chromium() as driver:
        yield driver


@pytest.fixture
def browser(one_chromium: Any) -> Iterator[Any]:
    driver = one_chromium
    driver.get("about:blank")
    driver.get_log("browser")  # what an earlier test's page said is not this test's
    try:
        yield driver
        # the page's event stream reconnecting to the server the test has stopped is not
        # the page's error (seen when a loaded machine is slow to end the test)
        errors = [e for e in console_errors(driver) if not (
            "/api/events" in e.get("message", "") and "ERR_CONNECTION_REFUSED" in e["message"])]
        assert not errors, f"errors in the browser console: {errors}"
    finally:  # the next test gets a blank page, at full size, light, without cookies
        driver.get("about:blank")
        driver.delete_all_cookies()
        phone(driver, False)
        color_scheme(driver, "light")


def screenshots(driver: Any, where: Path, name: str) -> None:
    """With ``RTUPOLL_DOCS_SCREENSHOTS=1``: light, dark and phone-width (dark) screenshots
    of the page as it is, into ``where``, and those docs/web.md shows into docs/."""
    if not os.environ.get("RTUPOLL_DOCS_SCREENSHOTS"):
        return
    for scheme, small in (("light", False), ("dark", False), ("dark", True)):
        color_scheme(driver, scheme)
        phone(driver, small)
        repainted(driver)
        shot = f"{name}{'-phone' if small else ''}{'-dark' if scheme == 'dark' else ''}.png"
        driver.save_screenshot(str(where / shot))
        if shot in IN_DOCS:
            driver.save_screenshot(str(DOCS / shot))
    phone(driver, False)
    color_scheme(driver, "light")


# the page's background and text colours, as drawn: [r, g, b] each
COLOURS = """
const rgb = c => c.match(/\\d+/g).slice(0, 3).map(Number);
const s = getComputedStyle(document.body);
return [rgb(s.backgroundColor), rgb(s.color)];
"""


def follows_the_system_scheme(driver: Any) -> None:
    """Light on a light system, dark on a dark one: the background and the text each
    take the other end of the scale (relative luminance, as WCAG computes it)."""
    def luminance(rgb: list[int]) -> float:
        lin = [c / 255 / 12.92 if c <= 10 else ((c / 255 + 0.055) / 1.055) ** 2.4
               for c in rgb]
        return 0.2126 * lin[0] + 0.7152 * lin[1] + 0.0722 * lin[2]

    try:
        for scheme in ("dark", "light"):
            color_scheme(driver, scheme)
            repainted(driver)
            bg, fg = (luminance(c) for c in driver.execute_script(COLOURS))
            dark = scheme == "dark"
            assert (bg < 0.1 and fg > 0.5) if dark else (bg > 0.8 and fg < 0.1), (scheme, bg, fg)
            assert (max(bg, fg) + 0.05) / (min(bg, fg) + 0.05) >= 7  # WCAG AAA contrast
    finally:
        color_scheme(driver, "light")


def test_the_demo_every_device_and_a_chart(browser: Any, tmp_path: Path) -> None:
    with running(["poll", "--simulate", "--format", "json", "--http", "127.0.0.1:0"],
                 tmp_path) as p:
        browser.get(p.url)
        page = until(lambda: (s := shown(browser)) and all(
            d["state"] == "online" for d in s.values()) and len(s) == 5 and s,
            "the five demo devices online on the page")
        assert sorted(page) == sorted(DEMO)
        state = get_json(p.url + "api/state")
        for dev in (d for gw in state["gateways"] for b in gw["buses"] for d in b["devices"]):
            assert list(page[dev["key"]]["fields"]) == [f["name"] for f in dev["fields"]]
            assert all(v.strip() for v in page[dev["key"]]["fields"].values()), dev["key"]
        # two lines, as the demo is wired
        assert browser.execute_script(
            "return Array.from(document.querySelectorAll('.bus')).map(b => b.dataset.bus)"
        ) == ["line1", "line2"]
        assert "5 of 5 devices online" in browser.find_element("id", "summary").text
        # a chart, opened by clicking the field, filled by the readings as they come
        click_chart(browser, "huiwen-aq@3", "co2", opened=True)
        until(lambda: (c := chart(browser, "huiwen-aq@3")) and c["points"] >= 3,
              "three points in the co2 chart")
        follows_the_system_scheme(browser)
        screenshots(browser, tmp_path, "web")
        # at a phone's width the page is one column and nothing sticks out sideways
        phone(browser, True)
        repainted(browser)
        assert browser.execute_script(
            "return document.documentElement.scrollWidth <= window.innerWidth")
        phone(browser, False)


def test_the_simulators_values_a_changing_field_drawn(
        browser: Any, sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "net-irnet-pro@1")
    for name, value in {"co2": 777, "temperature": 21, "humidity": 40}.items():
        bus.set(3, name, value)
    with running(["poll", "-p", bus.port, "-b", "9600", "--format", "json", "--interval",
                  "0.2", "--http", "127.0.0.1:0", "huiwen-aq@3", "net-irnet-pro@1"],
                 tmp_path) as p:
        browser.get(p.url)
        page = until(lambda: (s := shown(browser)) and "huiwen-aq@3" in s and
                     s["huiwen-aq@3"]["fields"]["co2"].startswith("777") and s,
                     "the pinned co2 on the page")
        air = page["huiwen-aq@3"]["fields"]
        assert air["co2"] == "777ppm"  # value and unit, in their own elements
        assert air["temperature"] == "21°C" and air["humidity"] == "40%RH"
        level = bus.get(3, "co2_level")
        assert page["huiwen-aq@3"]["badges"]["co2_level"][0].startswith(f"{level.value}:badge")
        assert set(page) == {"huiwen-aq@3", "net-irnet-pro@1"}
        # the field changes; its chart draws each 2 s step's point. The value changes as
        # the chart gains a point: the next step's point has another value than the last
        # (a change by the clock could fall twice in one step, and take four points)
        click_chart(browser, "huiwen-aq@3", "co2", opened=True)
        values = [700, 900, 650, 1100, 800, 950]

        def drawn() -> dict[str, Any] | None:
            c = chart(browser, "huiwen-aq@3")
            bus.set(3, "co2", values[(c["points"] if c else 0) % len(values)])
            return c if c and c["points"] >= 3 else None

        got = until(drawn, "three points of the changing co2 drawn", every=0.1)
        ys = got["ys"]
        assert len(ys) == got["points"] and len(set(ys)) >= 2, ys  # a line that moves
        assert got["note"].startswith(f"{len(ys)} points · min ") and got["note"].endswith("ppm")
        trend = get_json(p.url + "api/trend?device=huiwen-aq%403&field=co2")
        assert len(trend["v"]) >= len(ys) - 1
        # a second click closes it
        click_chart(browser, "huiwen-aq@3", "co2", opened=False)
        assert not browser.find_elements("css selector", "svg.trend")


def silence(bus: SimulatedBus, unit: int, dead: bool) -> None:
    """The simulated device at ``unit`` stops answering (``dead``) or answers again, from
    its next request: the test says when, by what the page shows, not by a schedule of
    request numbers that a loaded machine may run through before the page is there."""
    bus.device(unit).faults = FaultSet([parse_fault("dead")] if dead else [], 0, "test")


def test_a_dead_device_greys_out_and_comes_back(
        browser: Any, sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    # the room sensor at 4 stops answering once the page shows it online, and answers
    # again once the page shows it greyed out: it comes back after one backoff step (1 s).
    # (Not the radar: its blocks all have replies of one shape, so after a timeout the
    # line holds its next block until the timed-out request could no longer be answered,
    # 12 timeouts of its profile's 0.3 s: rtu/line.py, hazard_until. 3.6 s more.)
    bus = sim("huiwen-aq@3", "xy-md02@4")
    bus.set(4, "temperature", 21.5)  # every value starts with a digit
    with running(["poll", "-p", bus.port, "-b", "9600", "--format", "json", "--interval",
                  "0.3", "--timeout", "0.1", "--http", "127.0.0.1:0", "huiwen-aq@3",
                  "xy-md02@4"], tmp_path) as p:
        browser.get(p.url)
        until(lambda: shown(browser)["xy-md02@4"]["state"] == "online", "the room sensor online")
        silence(bus, 4, True)
        dead = until(lambda: (d := shown(browser)["xy-md02@4"])["down"] and d,
                     "the room sensor greyed out", every=0.05)
        silence(bus, 4, False)
        assert dead["state"] in ("retrying", "offline")
        assert dead["badge"].startswith(dead["state"] + ", ")  # next try in N s, or trying
        assert all(not v[:1].isdigit() for v in dead["fields"].values()), dead["fields"]
        assert "no reply" in " ".join(dead["fields"].values())
        assert "(last " in " ".join(dead["fields"].values())  # its last good value, dated
        assert not shown(browser)["huiwen-aq@3"]["down"]  # the other one carries on
        back = until(lambda: not (d := shown(browser)["xy-md02@4"])["down"] and
                     d["state"] == "online" and d, "the room sensor back by itself")
        assert all(v[:1].isdigit() for k, v in back["fields"].items() if k != "status")
        assert "timeouts" in back["health"] and "timeouts 0" not in back["health"]


def comparable(state: dict[str, Any]) -> dict[str, Any]:
    """Every device as the snapshot has it, without the reply-time percentiles (only in
    ``/api/state``: the events leave them out)."""
    out = {}
    for dev in devices(state).values():
        dev = json.loads(json.dumps(dev))
        for k in ("p50", "p95"):
            dev["health"].pop(k, None)
        out[dev["key"]] = dev
    return out


def test_the_pages_model_after_many_delta_events_is_the_servers_snapshot(
        browser: Any, tmp_path: Path) -> None:
    # a cycle every 0.5 s, not 1 s: the 60 events come in half the time
    with running(["poll", "--simulate", "--format", "json", "--interval", "0.5", "--http",
                  "127.0.0.1:0"], tmp_path) as p:
        browser.get(p.url)
        merged = "return window.rtupollPerf.events"
        until(lambda: browser.execute_script(merged) >= 30, "30 device events merged",
              every=0.2)
        # another client joins: every stream gets whole device events again, then deltas
        other = Events(p.url)
        kind, _ = next(iter(other))
        assert kind == "state"
        seen = browser.execute_script(merged)
        until(lambda: browser.execute_script(merged) >= seen + 30, "30 more", every=0.2)
        other.close()
        # each device, page and server read back to back until neither changed between
        # (a device changes only in its cycles, twice a second): equal, to the last key
        left = set(DEMO)
        diff: dict[str, Any] = {}
        deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
        while left and time.monotonic() < deadline:
            page = comparable(browser.execute_script("return window.rtupollModel()"))
            server = comparable(get_json(p.url + "api/state"))
            for key in list(left):
                if page[key] == server[key]:
                    left.discard(key)
                else:
                    diff[key] = [(k, page[key][k], server[key][k]) for k in server[key]
                                 if page[key].get(k) != server[key][k]]
            time.sleep(0.1)
        assert not left, {k: diff[k] for k in left}
        assert browser.execute_script(merged) >= seen + 30


# -- a fleet on one broker --------------------------------------------------------------

def info(gateway: str, devices: dict[str, dict[str, Any]]) -> str:
    return json.dumps({"gateway": gateway, "version": "0.1.0", "base": f"rtupoll/{gateway}",
                       "devices": devices})


AIR = {"profile": "huiwen-aq", "address": 3, "bus": "line1", "fields": {
    "co2": {"label": "CO2", "unit": "ppm", "kind": "number", "precision": 0},
    "co2_level": {"label": "CO2 level", "unit": "", "kind": "enum", "precision": None,
                  "severities": {"GOOD": "ok", "POOR": "warning"}, "unlisted": "warning"},
    "temperature": {"label": "temperature", "unit": "°C", "kind": "number", "precision": 1}}}


def publish(broker: Broker, topic: str, payload: str, *, retain: bool = True) -> None:
    subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                    *(["-r"] if retain else []), "-t", topic, "-m", payload], check=True,
                   timeout=30)


def test_the_fleet_two_gateways_on_one_broker(browser: Any, broker: Broker,
                                             tmp_path: Path) -> None:
    now = time.strftime("%Y-%m-%dT%H:%M:%S.000Z", time.gmtime())
    for gw, co2, temp in (("building-a", 612, 21.5), ("building-b", 1480, 23.4)):
        publish(broker, f"rtupoll/{gw}/bridge/info", info(gw, {"huiwen-aq@3": AIR}))
        publish(broker, f"rtupoll/{gw}/bridge/state", "online")
        publish(broker, f"rtupoll/{gw}/huiwen-aq_3/availability", "online")
        publish(broker, f"rtupoll/{gw}/huiwen-aq_3", json.dumps(
            {"co2": co2, "co2_level": "GOOD" if co2 < 1000 else "POOR", "temperature": temp,
             "last_seen": now, "_rtupoll": {"status": "ok"}}))
    publish(broker, "rtupoll/stray/thing", "not a gateway's")  # no bridge/info: ignored
    with running(["web", "--mqtt", broker.url, "--http", "127.0.0.1:0"], tmp_path,
                 name="web") as p:
        browser.get(p.url)
        page = until(lambda: len(s := shown(browser)) == 2 and s, "two gateways' devices")
        a, b = page["rtupoll/building-a/huiwen-aq_3"], page["rtupoll/building-b/huiwen-aq_3"]
        assert (a["gateway"], b["gateway"]) == ("building-a", "building-b")
        assert a["fields"] == {"co2": "612ppm", "co2_level": "GOOD", "temperature": "21.5°C"}
        assert b["fields"]["co2"] == "1480ppm" and b["fields"]["temperature"] == "23.4°C"
        assert b["badges"]["co2_level"] == ["POOR:badge sev-warning"]  # bridge/info's
        assert "2 gateways · 2 of 2 devices online" in browser.find_element("id", "summary").text
        # live: a new reading of one building, that building's card only
        publish(broker, "rtupoll/building-b/huiwen-aq_3", json.dumps(
            {"co2": 990, "co2_level": "GOOD", "temperature": 23.0, "last_seen": now}))
        until(lambda: shown(browser)["rtupoll/building-b/huiwen-aq_3"]["fields"]["co2"]
              == "990ppm", "building b's new co2")
        assert shown(browser)["rtupoll/building-a/huiwen-aq_3"]["fields"]["co2"] == "612ppm"
        # one gateway goes away (its last will): its section greys out, the other stays
        publish(broker, "rtupoll/building-a/bridge/state", "offline")
        publish(broker, "rtupoll/building-a/huiwen-aq_3/availability", "offline")
        gone = until(lambda: (s := shown(browser))["rtupoll/building-a/huiwen-aq_3"][
            "gatewayDown"] and s, "building a greyed out")
        assert gone["rtupoll/building-a/huiwen-aq_3"]["down"]
        # its retained values are no readings now: the last ones, dated, not as fresh
        assert gone["rtupoll/building-a/huiwen-aq_3"]["fields"]["co2"].startswith(
            "offline (last 612 ppm at ")
        assert not gone["rtupoll/building-b/huiwen-aq_3"]["gatewayDown"]
        assert "1 of 2 devices online" in browser.find_element("id", "summary").text
        screenshots(browser, tmp_path, "web-fleet")
        state = get_json(p.url + "api/state")
        assert state["mode"] == "fleet" and state["broker"] == "connected"
        assert [g["id"] for g in state["gateways"]] == ["building-a", "building-b"]


def test_the_fleet_keys_devices_by_their_topics(browser: Any, broker: Broker,
                                                tmp_path: Path) -> None:
    """Device ``x/y`` of the gateway at ``rtupoll/site`` (its topic level ``x_y``) and
    device ``y`` of the one at ``rtupoll/site/x``: one name joined to a base would be
    one key for both; each card shows its own reading."""
    probe = {"profile": "probe", "address": 1, "bus": "line1", "fields": {
        "temperature": {"label": "temperature", "unit": "°C", "kind": "number",
                        "precision": 1}}}
    publish(broker, "rtupoll/site/bridge/info", json.dumps(
        {"gateway": "site", "version": "0.1.0", "devices": {"x_y": {**probe, "name": "x/y"}}}))
    publish(broker, "rtupoll/site/x/bridge/info", json.dumps(
        {"gateway": "x", "version": "0.1.0", "devices": {"y": {**probe, "name": "y"}}}))
    publish(broker, "rtupoll/site/x_y", json.dumps({"temperature": 23.5}))
    publish(broker, "rtupoll/site/x/y", json.dumps({"temperature": 88.8}))
    with running(["web", "--mqtt", broker.url, "--http", "127.0.0.1:0"], tmp_path,
                 name="web") as p:
        browser.get(p.url)
        page = until(lambda: len(s := shown(browser)) == 2 and all(
            d["fields"]["temperature"] != "" for d in s.values()) and s, "both probes")
        assert page["rtupoll/site/x_y"]["fields"] == {"temperature": "23.5°C"}
        assert page["rtupoll/site/x/y"]["fields"] == {"temperature": "88.8°C"}
        assert (page["rtupoll/site/x_y"]["gateway"], page["rtupoll/site/x/y"]["gateway"]) == (
            "site", "x")
        # live: a new reading of one is that card's only
        publish(broker, "rtupoll/site/x/y", json.dumps({"temperature": 90.1}))
        until(lambda: shown(browser)["rtupoll/site/x/y"]["fields"]["temperature"] == "90.1°C",
              "the new reading of y")
        assert shown(browser)["rtupoll/site/x_y"]["fields"] == {"temperature": "23.5°C"}
        browser.save_screenshot(str(tmp_path / "fleet-keys.png"))


def test_the_fleet_page_with_hostile_retained_messages(browser: Any, broker: Broker,
                                                       tmp_path: Path) -> None:
    """A precision of 10^8, a 400-digit number, labels of 10,000 characters, a state
    that is not JSON: the page shows what it can, bounded, with no error in the
    console, and a good gateway's readings as they come."""
    huge = "9" * 400
    probe = {"profile": "probe", "address": 1, "bus": "line1", "fields": {
        "temperature": {"label": "temperature", "unit": "°C", "kind": "number",
                        "precision": 1}}}
    publish(broker, "rtupoll/good/bridge/info", json.dumps(
        {"gateway": "good", "version": "0.1.0", "devices": {"probe": probe}}))
    publish(broker, "rtupoll/good/probe", json.dumps({"temperature": 21.5}))
    publish(broker, "rtupoll/bad/bridge/info", json.dumps({"gateway": "bad", "devices": {
        "d": {"name": "n" * 10_000, "fields": {
            "v": {"label": "L" * 10_000, "kind": "number", "precision": 100_000_000},
            "w": {"kind": "number", "precision": -3}}}}}))
    publish(broker, "rtupoll/bad/d", f'{{"v": 1.25, "w": {huge}}}')
    publish(broker, "rtupoll/bad/d/availability", "x" * 5000)
    with running(["web", "--mqtt", broker.url, "--http", "127.0.0.1:0"], tmp_path,
                 name="web") as p:
        browser.get(p.url)
        page = until(lambda: len(s := shown(browser)) == 2 and
                     s["rtupoll/good/probe"]["fields"]["temperature"] and s, "both gateways")
        assert page["rtupoll/good/probe"]["fields"] == {"temperature": "21.5°C"}
        bad = page["rtupoll/bad/d"]["fields"]
        assert bad["v"] == "1.250000"
        publish(broker, "rtupoll/bad/d", "{not json", retain=False)
        publish(broker, "rtupoll/good/probe", json.dumps({"temperature": 22.5}), retain=False)
        until(lambda: shown(browser)["rtupoll/good/probe"]["fields"]["temperature"] ==
              "22.5°C", "the good gateway's next reading")
        browser.save_screenshot(str(tmp_path / "fleet-hostile.png"))


# each enum's or flag set's row and badges as drawn: severity class and colours
SEVERITIES = """
const out = {};
for (const r of document.querySelectorAll('tr.field')) {
  const badges = Array.from(r.querySelectorAll('.badge')).map(b => {
    const s = getComputedStyle(b);
    return [b.textContent, b.className, s.backgroundColor, s.color];
  });
  if (badges.length && !r.querySelector('.badge.none')) out[r.dataset.field] =
    {row: Array.from(r.classList).filter(c => c.startsWith('sev-')), badges: badges,
     value: getComputedStyle(r.querySelector('td.val')).color};
}
return out;
"""


def test_the_fleet_page_colours_readings_as_the_gateways_dashboard(
        browser: Any, broker: Broker, sim: Callable[..., SimulatedBus],
        tmp_path: Path) -> None:
    """A real gateway (``poll --mqtt --http``) polling a Huiwen whose CO2 level is
    MODERATE (a warning) and whose CO2 sensor is SENSOR_ABNORMAL (an error), and ``web
    --mqtt`` on the same broker: the fleet page's rows and badges have the dashboard's
    severities and colours, from what the gateway publishes."""
    bus = sim("huiwen-aq@3", tcp=True, tick=None)
    bus.set(3, "co2_level", "MODERATE")
    bus.set(3, "co2_failure", "SENSOR_ABNORMAL")
    with gateway_and_fleet(broker.url, bus.port, "huiwen-aq@3", tmp_path) as (east, web):
        pages = {}
        for name, p in (("dashboard", east), ("fleet", web)):
            browser.get(p.url)
            pages[name] = until(lambda: (s := browser.execute_script(SEVERITIES)).get(
                "co2_failure") and s["co2_failure"]["badges"][0][0] == "SENSOR_ABNORMAL"
                and s, f"the {name}'s CO2 sensor abnormal", limit=90)
            browser.save_screenshot(str(tmp_path / f"severity-{name}.png"))
        ours, theirs = pages["dashboard"], pages["fleet"]
        assert ours["co2_level"]["row"] == ["sev-warning"]
        assert ours["co2_level"]["badges"][0][:2] == ["MODERATE", "badge sev-warning"]
        assert ours["co2_failure"]["row"] == ["sev-error"]
        assert ours["co2_failure"]["badges"][0][:2] == ["SENSOR_ABNORMAL", "badge sev-error"]
        assert ours["pm25_failure"]["badges"][0][:2] == ["NO_FAULT", "badge sev-ok"]
        assert len(ours) >= 9  # the Huiwen's nine enums
        assert theirs == ours  # every enum's row, badges and colours


def test_the_fleet_page_names_a_sentinel_as_the_gateways_dashboard(
        browser: Any, broker: Broker, sim: Callable[..., SimulatedBus],
        tmp_path: Path) -> None:
    """A real gateway polling an R4DCB08 whose first channel has no sensor (its
    profile's sentinel 0x8000, NO_SENSOR, an error): the dashboard shows the name, a
    badge of its severity, and so does the fleet page, from what the gateway publishes
    (``_rtupoll.sentinels``), where it said "no reading"."""
    bus = sim("r4dcb08@1", tcp=True, tick=None)
    bus.set(1, "temperature_1", "NO_SENSOR")
    bus.set(1, "temperature_2", 21.5)
    with gateway_and_fleet(broker.url, bus.port, "r4dcb08@1", tmp_path) as (east, web):
        pages, rows = {}, {}
        for name, p in (("dashboard", east), ("fleet", web)):
            browser.get(p.url)
            pages[name] = until(lambda: (s := browser.execute_script(SEVERITIES)).get(
                "temperature_1") and s, f"the {name}'s NO_SENSOR", limit=90)
            (rows[name],) = until(lambda: [d for d in shown(browser).values()
                                           if d["fields"].get("temperature_2") == "21.5°C"],
                                  f"the {name}'s second channel")
            browser.save_screenshot(str(tmp_path / f"sentinel-{name}.png"))
        ours, theirs = pages["dashboard"], pages["fleet"]
        assert ours["temperature_1"]["row"] == ["sev-error"]
        assert ours["temperature_1"]["badges"][0][:2] == ["NO_SENSOR", "badge sev-error"]
        assert theirs == ours  # the row, its badge and their colours
        assert rows["fleet"]["fields"]["temperature_1"] == \
            rows["dashboard"]["fields"]["temperature_1"] == "NO_SENSOR"
        assert rows["fleet"]["fields"]["temperature_2"] == "21.5°C"
