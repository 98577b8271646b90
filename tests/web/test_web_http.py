"""The dashboard over HTTP: ``/api/state``, ``/api/events``, ``/api/trend``, ``/metrics``,
authentication, and the options' errors, against a real ``rtupoll poll --http`` polling
simulated devices."""

from __future__ import annotations

import base64
import http.client
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_runner import Ran, rtupoll

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port
from tests.web_helpers import Events, devices, field, get, get_json, merge, running, until

POLL = ["poll", "--format", "json", "--interval", "0.2", "--timeout", "0.1"]


def test_state_events_trend_and_metrics_of_a_polling_process(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "net-irnet-pro@1", "radar-level@4", faults=["4:dead"])
    for name, value in {"co2": 777, "temperature": 21, "humidity": 40}.items():
        bus.set(3, name, value)
    with running([*POLL, "-p", bus.port, "-b", "9600", "--http", "127.0.0.1:0", "huiwen-aq@3",
                  "net-irnet-pro@1", "radar-level@4"], tmp_path, fresh=True) as p:
        url = p.url
        assert url.startswith("http://127.0.0.1:")

        def polled() -> dict[str, Any] | None:
            st = get_json(url + "api/state")
            devs = devices(st)
            ok = devs["huiwen-aq@3"]["state"] == "online" and \
                devs["radar-level@4"]["state"] in ("retrying", "offline")
            return st if ok else None

        state = until(polled, "the live device online and the dead one backed off")
        assert state["mode"] == "poll" and state["span"] == 3600
        gw = state["gateways"][0]
        assert [b["name"] for b in gw["buses"]] == [bus.port]
        devs = devices(state)
        assert list(devs) == ["huiwen-aq@3", "net-irnet-pro@1", "radar-level@4"]
        air = devs["huiwen-aq@3"]
        assert air["profile"] == "huiwen-aq" and air["address"] == 3
        co2 = field(air, "co2")
        assert (co2["value"], co2["unit"], co2["kind"], co2["status"]) == (777, "ppm",
                                                                           "number", "ok")
        assert field(air, "temperature")["value"] == 21
        assert field(air, "humidity")["value"] == 40
        level = field(air, "co2_level")
        assert level["kind"] == "enum" and level["badges"] == [
            {"name": level["value"], "severity": level["severity"]}]
        health = air["health"]
        assert health["ok"] > 0 and health["timeouts"] == 0 and health["last_seen"] > 0
        assert health["timeout"] is not None and health["next_try"] is None
        # the dead device: no values at all, only why; its next try is announced
        dead = devs["radar-level@4"]
        assert dead["health"]["ok"] == 0 and dead["health"]["timeouts"] >= 1
        assert dead["health"]["last_seen"] is None
        assert dead["health"]["next_try"] > state["time"] - 1
        assert all(f["value"] is None and f["status"] in ("timeout", "skipped")
                   for f in dead["fields"])
        # flags of the gas sensor: the active ones, named
        flags = [f for f in devs["net-irnet-pro@1"]["fields"] if f["kind"] == "flags"]
        assert flags and all(isinstance(f["value"], list) for f in flags)

        # the event stream: the snapshot first, then one event per device cycle, with
        # every field's time but only the fields whose reading changed
        events = Events(url)
        try:
            it = iter(events)
            kind, model = next(it)
            assert kind == "state" and devices(model).keys() == devs.keys()
            seen: dict[str, int] = {}
            values: set[float] = set()
            sent: list[set[str]] = []  # the fields of each event of the gas sensor
            bus.set(3, "co2", 901)
            for kind, data in it:
                if kind == "device":
                    key = data["device"]["key"]
                    seen[key] = seen.get(key, 0) + 1
                    assert "p50" not in data["device"]["health"]
                    dev = merge(model, data)
                    assert dev is not None
                    assert len(data["device"]["times"]) == len(dev["fields"])
                    if key == "huiwen-aq@3":
                        values.add(field(dev, "co2")["value"])
                        sent.append({f["name"] for f in data["device"]["fields"]})
                if 901 in values and len(seen) == 3 and min(seen.values()) >= 1 and \
                        seen["huiwen-aq@3"] >= 3:
                    break
        finally:
            events.close()
        # the first event after the snapshot has every field; then only what changed:
        # temperature and humidity are held, co2 changed (at most) once
        assert sent[0] == {f["name"] for f in air["fields"]}
        assert all("temperature" not in s and "humidity" not in s for s in sent[1:])
        assert sum("co2" in s for s in sent[1:]) <= 1
        assert 901 in values

        # the trend of co2: a point per 2 s step it was polled in, the newest last
        trend = until(lambda: (t := get_json(url + "api/trend?device=huiwen-aq%403&field=co2"))
                      and len(t["t"]) >= 2 and t["v"][-1] == 901 and t,
                      "two points in the trend, 901 the last")
        assert len(trend["t"]) == len(trend["v"])
        assert all(b > a for a, b in zip(trend["t"], trend["t"][1:], strict=False))
        # polled every 0.2 s, kept one per 2 s step
        assert len(trend["t"]) <= (trend["t"][-1] - trend["t"][0]) / 2 + 2
        assert trend["t"][-1] <= time.time() + 1
        assert get_json(url + "api/trend?device=nobody&field=co2") == {"t": [], "v": []}
        assert get(url + "api/trend")[0] == 400

        # /metrics on the same listener, Prometheus text from outputs.metrics
        status, headers, body = get(url + "metrics")
        assert status == 200 and headers["Content-Type"].startswith("text/plain")
        sample = 'rtupoll_co2_ppm{bus="' + bus.port + '",device="huiwen-aq@3"} 901.0'
        assert sample in body.decode()
        # the page and its assets, from the package
        status, headers, page = get(url)
        assert status == 200 and b"/static/app.js" in page
        assert "default-src 'self'" in headers["Content-Security-Policy"]
        for name in ("app.js", "style.css", "icon.svg"):
            assert get(url + "static/" + name)[0] == 200
        assert get(url + "static/nothing.js")[0] == 404
        # read-only
        conn = http.client.HTTPConnection(url.split("//")[1].rstrip("/"), timeout=10)
        conn.request("POST", "/api/state", body=b"{}")
        assert conn.getresponse().status == 405
        conn.close()
        # a reconnection, with the id a browser's EventSource would send back, starts
        # with a snapshot again: whatever it missed is in it
        again = Events(url, headers={"Last-Event-ID": "41"})
        try:
            kind, snap = next(iter(again))
        finally:
            again.close()
        assert kind == "state" and field(devices(snap)["huiwen-aq@3"], "co2")["value"] == 901
        # a browser still connected when poll stops: it stops anyway, cleanly
        held = Events(url)
        code = p.stop()
        held.close()
    assert code == 0, p.stderr()
    assert f"dashboard on {url}" in p.stderr()


def test_bearer_token_cookie_and_basic_auth(sim: Callable[..., SimulatedBus],
                                            tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    token = "s3cret-token-for-the-page"
    with running([*POLL, "-p", bus.port, "--http", "127.0.0.1:0", "--http-token", token,
                  "--http-user", "tech:correct-horse", "huiwen-aq@3"], tmp_path) as p:
        url = p.url
        for path in ("", "api/state", "api/events", "metrics", "static/app.js"):
            status, headers, _ = get(url + path)
            assert status == 401, path
            assert headers["WWW-Authenticate"] == 'Bearer realm="rtupoll", Basic realm="rtupoll"'
        assert get(url + "api/state", {"Authorization": "Bearer wrong-token-here"})[0] == 401
        assert get(url + "api/state", {"Authorization": f"Bearer {token}"})[0] == 200
        basic = base64.b64encode(b"tech:correct-horse").decode()
        assert get(url + "api/state", {"Authorization": f"Basic {basic}"})[0] == 200
        wrong = base64.b64encode(b"tech:wrong-horse").decode()
        assert get(url + "api/state", {"Authorization": f"Basic {wrong}"})[0] == 401
        assert get(url + "api/state", {"Authorization": "Basic !!!"})[0] == 401
        # a browser: /?token= once, then a cookie (not the token itself), token out of the URL
        conn = http.client.HTTPConnection(url.split("//")[1].rstrip("/"), timeout=10)
        conn.request("GET", f"/?token={token}")
        resp = conn.getresponse()
        assert resp.status == 303 and resp.getheader("Location") == "/"
        cookie = resp.getheader("Set-Cookie") or ""
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and token not in cookie
        resp.read()
        conn.close()
        jar = cookie.split(";")[0]
        assert get(url + "api/state", {"Cookie": jar})[0] == 200
        assert get(url + "api/state", {"Cookie": "rtupoll_token=forged"})[0] == 401
    assert "readable by anyone" not in p.stderr()


def test_an_open_dashboard_on_the_network_is_warned_about(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    port = free_port()
    with running([*POLL, "-p", bus.port, "--http", f"0.0.0.0:{port}", "huiwen-aq@3"],
                 tmp_path) as p:
        assert get_json(f"http://127.0.0.1:{port}/api/state")["mode"] == "poll"
    assert (f"rtupoll: --http 0.0.0.0:{port}: the dashboard is readable by anyone who can "
            "reach this port; guard it with --http-token or --http-user (docs/web.md)"
            in p.stderr())


def test_the_site_files_http_section(sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    site = tmp_path / "site.yaml"
    site.write_text(f"http:\n  listen: 127.0.0.1:0\n  users: {{tech: correct-horse}}\n"
                    f"buses:\n  - port: {bus.port}\n    baudrate: 9600\n    devices:\n"
                    f"      - {{profile: huiwen-aq, address: 3, interval: 0.2}}\n")
    with running(["poll", "--format", "json", "-c", str(site)], tmp_path) as p:
        assert get(p.url + "api/state")[0] == 401
        basic = base64.b64encode(b"tech:correct-horse").decode()
        state = get_json(p.url + "api/state", {"Authorization": f"Basic {basic}"})
        assert list(devices(state)) == ["huiwen-aq@3"]


def run_cli(*args: str) -> Ran:
    return rtupoll(*args)


@pytest.mark.parametrize(("args", "message"), [
    (["--http", "nowhere"], "--http 'nowhere': expected [HOST:]PORT, e.g. 127.0.0.1:8080"),
    (["--http", "8080", "--http-token", "short"],
     "--http-token is shorter than 8 characters"),
    (["--http", "8080", "--http-user", "tech"], "--http-user 'tech': expected USER:PASSWORD"),
    (["--http-token", "long-enough-token"],
     "--http-token, --http-user and the --http-... limits need --http HOST:PORT (or http: "
     "in the site file)"),
    (["--http", "8080", "--http-header-timeout", "0"],
     "--http-header-timeout 0 is not a number of seconds in (0, 3600]"),
    (["--http", "8080", "--http-idle-timeout", "nan"],
     "--http-idle-timeout nan is not a number of seconds in (0, 3600]"),
    (["--http", "8080", "--http-max-connections", "0"],
     "--http-max-connections 0 is outside 1..100000"),
    (["--http", "8080", "--http-host", "evil.com:80"],
     "--http-host 'evil.com:80' is not a host name (a name or an address, no port)"),
])
def test_bad_http_options_are_one_line_exit_2(sim: Callable[..., SimulatedBus],
                                              args: list[str], message: str) -> None:
    bus = sim("huiwen-aq@3")
    got = run_cli("poll", "-p", bus.port, *args, "huiwen-aq@3")
    assert got.returncode == 2, got.stderr
    assert got.stderr.strip().splitlines()[-1] == f"rtupoll: {message}"


def test_a_busy_port_is_one_line_exit_2(sim: Callable[..., SimulatedBus],
                                        tmp_path: Path) -> None:
    bus, other = sim("huiwen-aq@3"), sim("huiwen-aq@3")
    with running([*POLL, "-p", bus.port, "--http", "127.0.0.1:0", "huiwen-aq@3"],
                 tmp_path) as first:
        port = first.url.rsplit(":", 1)[1].rstrip("/")
        got = run_cli("poll", "-p", other.port, "--format", "json", "--http",
                      f"127.0.0.1:{port}", "huiwen-aq@3")
    assert got.returncode == 2, got.stderr
    assert got.stderr.strip().splitlines()[-1] == (
        f"rtupoll: --http: cannot listen on 127.0.0.1:{port}: Address already in use")


def test_rtupoll_web_without_a_broker_is_one_line_exit_10() -> None:
    port = free_port()  # nothing listens there
    got = run_cli("web", "--mqtt", f"mqtt://127.0.0.1:{port}", "--http", "127.0.0.1:0")
    assert got.returncode == 10, got.stderr
    assert got.stderr.strip().splitlines() == [
        f"rtupoll: --mqtt mqtt://127.0.0.1:{port}: connection refused (is the broker "
        f"running on port {port}?)"]


def test_rtupoll_web_bad_arguments_are_one_line_exit_2() -> None:
    got = run_cli("web", "--mqtt", "http://broker")
    assert got.returncode == 2
    assert got.stderr.strip().splitlines()[-1].startswith("rtupoll: --mqtt http://broker: "
                                                          "expected mqtt://")
    got = run_cli("web", "--mqtt", "mqtt://broker", "--http", "nowhere")
    assert got.returncode == 2
    assert got.stderr.strip().splitlines()[-1] == (
        "rtupoll: --http 'nowhere': expected [HOST:]PORT, e.g. 127.0.0.1:8080")


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll is not installed "
                    "(scripts/test installs it)")
def test_the_gateways_clients_and_queue_with_serve(sim: Callable[..., SimulatedBus],
                                                   tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    serve = free_port()
    with running([*POLL, "-p", bus.port, "--serve", f"127.0.0.1:{serve}", "--http",
                  "127.0.0.1:0", "huiwen-aq@3"], tmp_path) as p:
        gw = get_json(p.url + "api/state")["gateways"][0]["buses"][0]["gateway"]
        assert gw == {"bus": bus.port, "listen": f"tcp://127.0.0.1:{serve}", "pending": 0,
                      "clients": []}
        # mbpoll, another master, reads the CO2 register through the gateway
        done = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(serve), "-1", "-o", "2",
                               "-a", "3", "-t", "3", "-r", "30009", "-0", "-c", "1",
                               "127.0.0.1"], capture_output=True, text=True, timeout=30)
        assert done.returncode == 0, done.stdout + done.stderr
        state = get_json(p.url + "api/state")
        (client,) = state["gateways"][0]["buses"][0]["gateway"]["clients"]
        assert client["requests"] == client["answered"] == 1
        # the same in the periodic buses event
        events = Events(p.url)
        try:
            _, data = next((k, d) for k, d in events if k == "buses")
        finally:
            events.close()
        (b,) = data["buses"]
        assert b["gateway"]["clients"][0]["requests"] == 1 and "devices" not in b
