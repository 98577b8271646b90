"""Prometheus metrics: ``rtupoll poll --metrics HOST:PORT`` scraped over real HTTP.

The end-to-end test runs the real command in a subprocess against a simulated bus
with one dead device, scrapes ``/metrics`` twice and parses the exposition with
``prometheus_client``'s own parser. The others drive the collector in-process.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import Ran, rtupoll
from forked_cli import rtupoll_popen
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families
from virtual import simulated

from rtupoll.config.library import load_one
from rtupoll.config.site import from_specs
from rtupoll.errors import install_command
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.outputs.metrics import SchedulerCollector, field_metric, parse_listen
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def parse(text: str) -> Samples:
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[s.name, tuple(sorted(s.labels.items()))] = s.value
    return out


def get(samples: Samples, name: str, **labels: str) -> float | None:
    return samples.get((name, tuple(sorted(labels.items()))))


def scrape(port: int, path: str = "/metrics") -> str:
    # (30 s: a hang guard, the answer ends it; a busy machine's server may be slow to it)
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30) as r:
        body: bytes = r.read()
        assert r.status == 200
    return body.decode()


def test_scraped_over_http_while_polling_with_a_dead_device(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:dead"])
    for name, value in {"co2": 777, "temperature": 21, "humidity": 40,
                        "co2_level": "GOOD"}.items():
        bus.set(3, name, value)
    port = free_port()
    err = (tmp_path / "stderr").open("w")
    proc = rtupoll_popen(
        [sys.executable, "-m", "rtupoll", "poll", "-p", bus.port, "--format", "json",
         "--interval", "0.2", "--timeout", "0.1", "--metrics", f"127.0.0.1:{port}",
         "--log-format", "text",
         "huiwen-aq@3", "radar-level@4"],
        stdout=subprocess.DEVNULL, stderr=err)
    try:
        first: Samples = {}
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                first = parse(scrape(port))
                cycles = get(first, "rtupoll_cycles_total", bus=bus.port, device="radar-level@4")
                if (cycles or 0) >= 2 and get(first, "rtupoll_device_up", bus=bus.port,
                                              device="huiwen-aq@3") == 1:
                    break
            time.sleep(0.1)
        live = {"bus": bus.port, "device": "huiwen-aq@3"}
        dead = {"bus": bus.port, "device": "radar-level@4"}
        assert get(first, "rtupoll_device_up", **live) == 1
        assert get(first, "rtupoll_device_up", **dead) == 0
        # the pinned values, in base units where the profile's unit has one
        assert get(first, "rtupoll_co2_ppm", **live) == 777
        assert get(first, "rtupoll_temperature_celsius", **live) == 21
        assert get(first, "rtupoll_humidity_ratio", **live) == pytest.approx(0.40)
        assert get(first, "rtupoll_co2_level_state", **live, state="GOOD") == 1
        assert get(first, "rtupoll_co2_level_state", **live, state="SEVERE") == 0
        assert get(first, "rtupoll_co2_level_code", **live) is not None
        # the dead device: no readings at all, timeouts counted, no good reading ever
        assert not [k for k in first if k[0].startswith(("rtupoll_air_gap", "rtupoll_level"))]
        assert (get(first, "rtupoll_requests_total", **dead, outcome="timeout") or 0) >= 2
        assert get(first, "rtupoll_requests_total", **dead, outcome="ok") == 0
        assert get(first, "rtupoll_last_good_reading_age_seconds", **dead) is None
        assert get(first, "rtupoll_last_good_reading_age_seconds", **live) is not None
        assert get(first, "rtupoll_device_info", **live, profile="huiwen-aq", address="3") == 1
        assert get(first, "rtupoll_bus_port_up", bus=bus.port) == 1
        assert (get(first, "rtupoll_request_duration_seconds_count", **live) or 0) > 0
        # an honest device's reply is late only after an attempt of it timed out (a loaded
        # machine can delay the simulator past the pinned 0.1 s; then a retry may take the
        # answer, and the request is ok): never more late replies than timed-out attempts,
        # the requests that timed out and the retries (attempts on the wire, counted
        # after the scrape, less requests)
        late = get(first, "rtupoll_late_replies_total", **live)
        requests = {o: get(first, "rtupoll_requests_total", **live, outcome=o) or 0
                    for o in ("ok", "timeout", "garbled", "exception")}
        attempts = sum(w.direction == "in" and w.data[:1] == b"\x03" for w in bus.wire)
        assert late is not None and late <= requests["timeout"] + (
            attempts - sum(requests.values())), (late, requests, attempts)
        assert get(first, "rtupoll_device_timeout_seconds", **dead) == pytest.approx(0.1)
        util = get(first, "rtupoll_bus_utilisation_ratio", bus=bus.port)
        assert util is not None and 0 < util <= 1

        counters = [k for k in first if k[0].endswith(("_total", "_count", "_bucket", "_sum"))]
        second, deadline = first, time.monotonic() + 30  # (a hang guard): until it polled on
        while sum(second[k] for k in counters) <= sum(first[k] for k in counters) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
            second = parse(scrape(port))
        assert len(counters) > 20
        assert all(second[k] >= first[k] for k in counters), "a counter went down"
        assert sum(second[k] for k in counters) > sum(first[k] for k in counters)
        with pytest.raises(urllib.error.HTTPError) as nope:
            scrape(port, "/nothing")
        assert nope.value.code == 404
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=20)
        err.close()
    log = (tmp_path / "stderr").read_text()
    assert code == 0, log
    assert f"serving metrics on http://127.0.0.1:{port}/metrics" in log
    # the dead device is logged once when it stops answering, not every scan
    assert log.count("radar-level@4 on") == 1, log


async def _cycles(scheduler: Scheduler, n: int, collector: SchedulerCollector) -> None:
    bp = scheduler.buses[0]

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        collector.observe(bp, dev, readings)

    await scheduler.open()
    try:
        for _ in range(n):
            await scheduler.scan_once(sink)
    finally:
        await scheduler.close()


def test_a_device_that_dies_loses_its_readings_and_its_up() -> None:
    # in virtual time (tests/virtual.py): a 0.05 s timeout on a real pty failed a live
    # answer on a busy machine; the metrics are what is tested here, not the port
    bus, clock = simulated(["radar-level@4"], ["4:dead@6-"])  # 5 fields, one read each:
    bus.engine.device(4).pin("level_cm", 150)  # 1 good cycle
    scheduler = Scheduler(from_specs("virtual", [("radar-level", 4)], timeout=0.05, retries=0,
                                     check_serial=False),
                          open_bus=lambda _: bus, clock=clock)
    collector = SchedulerCollector(scheduler)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    labels = {"bus": "virtual", "device": "radar-level@4"}

    asyncio.run(_cycles(scheduler, 1, collector))
    alive = parse(generate_latest(registry).decode())
    assert get(alive, "rtupoll_level_cm", **labels) == 150
    assert get(alive, "rtupoll_device_up", **labels) == 1

    asyncio.run(_cycles(scheduler, 1, collector))
    gone = parse(generate_latest(registry).decode())
    assert get(gone, "rtupoll_level_cm", **labels) is None  # not its last value
    assert get(gone, "rtupoll_device_up", **labels) == 0
    assert get(gone, "rtupoll_device_state", **labels, state="retrying") == 1
    assert get(gone, "rtupoll_requests_total", **labels, outcome="timeout") == 1
    assert (get(gone, "rtupoll_last_good_reading_age_seconds", **labels) or -1) >= 0


def test_names_follow_the_base_units() -> None:
    irnet, huiwen, radar = (load_one(p) for p in ("net-irnet-pro", "huiwen-aq", "radar-level"))
    kelvin = field_metric(irnet.field("temperature"))
    assert kelvin.name == "rtupoll_temperature_celsius"
    assert kelvin.convert(296.15) == pytest.approx(23.0)
    assert field_metric(huiwen.field("temperature")).name == "rtupoll_temperature_celsius"
    assert field_metric(huiwen.field("humidity")).convert(45) == pytest.approx(0.45)
    assert field_metric(huiwen.field("co2")).name == "rtupoll_co2_ppm"
    # the name already says its unit: kept, not converted (cm and mm would collide)
    level = field_metric(radar.field("level_cm"))
    assert (level.name, level.convert(150)) == ("rtupoll_level_cm", 150.0)
    assert field_metric(irnet.field("error")).kind == "enum"
    assert field_metric(irnet.field("warning")).kind == "flags"


def test_base_units_counters_precision_and_help() -> None:
    irnet, huiwen, sdm120, rover = (load_one(p) for p in (
        "net-irnet-pro", "huiwen-aq", "eastron-sdm120", "renogy-rover"))
    kelvin = field_metric(irnet.field("temperature"))
    assert kelvin.convert(296.67) == 23.52  # exactly: no 23.52000000000004
    assert kelvin.help == field_metric(huiwen.field("temperature")).help == \
        "Field temperature, in celsius"  # the family's unit, not one profile's K
    pm25 = field_metric(huiwen.field("pm25"))
    assert (pm25.name, pm25.convert(18)) == ("rtupoll_pm25_grams_per_cubic_meter", 1.8e-05)
    energy = field_metric(sdm120.field("import_active_energy"))
    assert (energy.name, energy.kind) == ("rtupoll_import_active_energy_joules", "counter")
    assert energy.convert(1532.251) == 5516103600.0
    assert field_metric(sdm120.field("import_reactive_energy")).kind == "counter"
    assert field_metric(sdm120.field("voltage")).kind == "gauge"
    amp_hours = [f for f in rover.fields if f.unit == "Ah"]
    assert amp_hours and all("hours" not in field_metric(f).name and
                             field_metric(f).name.endswith("_coulombs") for f in amp_hours)
    assert field_metric(amp_hours[0]).name == "rtupoll_charging_today_coulombs"
    assert field_metric(amp_hours[0]).convert(12) == 43200.0
    # promtool refuses abbreviated units in a name (_m_s, _s_cm, _m): base units instead
    wind, soil, sun = (load_one(p) for p in ("dfrobot-sen0483", "sensecap-soil-ec02",
                                             "huawei-sun2000"))
    speed = field_metric(wind.field("wind_speed"))
    assert (speed.name, speed.convert(3.7)) == ("rtupoll_wind_speed_meters_per_second", 3.7)
    ec = field_metric(soil.field("conductivity"))
    assert (ec.name, ec.convert(850)) == ("rtupoll_conductivity_siemens_per_meter", 0.085)
    riso = field_metric(sun.field("insulation_resistance"))
    assert (riso.name, riso.convert(3.0)) == ("rtupoll_insulation_resistance_ohms", 3e6)


def test_listen_addresses() -> None:
    assert parse_listen("127.0.0.1:9100") == ("127.0.0.1", 9100)
    assert parse_listen(":9100") == ("127.0.0.1", 9100)  # loopback, as --serve
    assert parse_listen("0.0.0.0:9100") == ("0.0.0.0", 9100)
    assert parse_listen("[::1]:9100") == ("::1", 9100)
    assert parse_listen("[::]:9100") == ("::", 9100)


def poll(*args: str) -> Ran:
    return rtupoll("poll", *args)


def test_a_bad_or_busy_address_is_one_line_exit_2(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3")
    bad = poll("-p", bus.port, "--once", "--metrics", "localhost", "huiwen-aq@3")
    assert bad.returncode == 2
    assert bad.stderr.strip() == ("rtupoll: --metrics 'localhost': expected [HOST:]PORT, "
                                  "e.g. 127.0.0.1:9464")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        busy = poll("-p", bus.port, "--once", "--metrics", f"127.0.0.1:{port}", "huiwen-aq@3")
    assert busy.returncode == 2
    assert busy.stderr.startswith(f"rtupoll: --metrics: cannot listen on 127.0.0.1:{port}: ")
    assert len(busy.stderr.splitlines()) == 1


def test_without_prometheus_client_it_says_what_to_install(
        sim: Callable[..., SimulatedBus], monkeypatch: pytest.MonkeyPatch) -> None:
    bus = sim("huiwen-aq@3")
    monkeypatch.setitem(sys.modules, "prometheus_client", None)  # import fails
    result = poll("-p", bus.port, "--once", "--metrics", "127.0.0.1:0", "huiwen-aq@3")
    assert result.returncode == 2
    assert result.stderr.strip() == ("rtupoll: --metrics needs prometheus_client: "
                                     + install_command("metrics")[1])


def test_metrics_in_the_site_file(tmp_path: Path) -> None:
    from rtupoll.config.site import load_site
    from rtupoll.errors import ConfigError

    path = tmp_path / "site.yaml"
    body = ("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n    devices:\n"
            "      - {profile: huiwen-aq, address: 3}\n")
    path.write_text("metrics: 127.0.0.1:9464\n" + body)
    assert load_site(path).metrics == "127.0.0.1:9464"
    path.write_text(body + "metrics: 9464\n")  # a port alone: loopback, as --metrics 9464
    assert load_site(path).metrics == "9464"
    path.write_text(body + "metrics: localhost\n")
    with pytest.raises(ConfigError) as bad:
        load_site(path)
    assert str(bad.value) == (f"{path}:6: metrics: 'localhost': expected [HOST:]PORT, "
                              "e.g. 127.0.0.1:9464")


@pytest.mark.parametrize("given", ["9464", ":9464", "127.0.0.1:9464"])
def test_metrics_http_and_serve_take_a_listen_address_alike(given: str) -> None:
    """One rule (config/listen.py): a port alone is loopback, for each of the three."""
    from rtupoll.config.gateway_settings import parse_listen as serve
    from rtupoll.config.http_settings import parse_listen as http
    from rtupoll.outputs.metrics import parse_listen as metrics

    assert metrics(given) == http(given) == serve(given)[1:] == ("127.0.0.1", 9464)


def test_a_nan_register_is_no_sample_and_no_influx_field(
        sim: Callable[..., SimulatedBus]) -> None:
    from rtupoll.outputs.influx import lines

    bus = sim("net-irnet-pro@1")
    bus.set(1, "concentration", float("nan"))
    bus.set(1, "temperature", 296.15)
    site = from_specs(bus.port, [("net-irnet-pro", 1)], baudrate=9600, check_serial=False)
    scheduler = Scheduler(site)
    collector = SchedulerCollector(scheduler)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    asyncio.run(_cycles(scheduler, 1, collector))
    text = generate_latest(registry).decode()
    samples = parse(text)
    labels = {"bus": bus.port, "device": "net-irnet-pro@1"}
    assert get(samples, "rtupoll_temperature_celsius", **labels) == pytest.approx(23.0)
    assert get(samples, "rtupoll_concentration_ppm", **labels) is None
    assert all(v == v for v in samples.values())  # no NaN sample anywhere
    assert not [line for line in text.splitlines() if line.endswith(("NaN", "nan"))]
    readings = list(scheduler.pollers()[0].stats.latest.values())
    assert any(r.value is not None and r.field.name == "concentration" for r in readings)
    out = "\n".join(lines(readings))
    assert "concentration=" not in out and "temperature=296.15" in out
    assert not [f for f in out.replace(" ", ",").split(",") if f.lower().endswith("=nan")]


def test_the_gateways_clients_are_on_the_same_metrics_page() -> None:
    metrics, serve = free_port(), free_port()
    proc = rtupoll_popen(
        [sys.executable, "-m", "rtupoll", "poll", "--simulate", "huiwen-aq@3", "--format",
         "json", "--serve", f"127.0.0.1:{serve}", "--metrics", f"127.0.0.1:{metrics}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        samples: Samples = {}
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline and not samples:
            with contextlib.suppress(OSError):
                samples = parse(scrape(metrics))
            time.sleep(0.1)
        gateway = [k for k in samples if k[0] == "rtupoll_gateway_clients"]
        assert gateway and samples[gateway[0]] == 0  # served, nobody connected yet
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=20)
    assert proc.returncode == 0


def _non_loopback_ipv4() -> str | None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s, contextlib.suppress(OSError):
        s.connect(("192.0.2.1", 9))  # no packet is sent: only a route is chosen
        host = str(s.getsockname()[0])
        return None if host.startswith("127.") or host == "0.0.0.0" else host
    return None


def test_where_metrics_listen() -> None:
    """``:PORT`` is loopback only (as ``--serve``); ``[::]:PORT`` takes IPv6 and IPv4."""
    from rtupoll.outputs.metrics import MetricsService

    site = from_specs("/dev/null", [("huiwen-aq", 3)], check_serial=False)

    def get(host: str, port: int, family: int, timeout: float = 30) -> bytes:
        with socket.socket(family) as s:
            s.settimeout(timeout)  # (a hang guard where it is served: the answer ends it)
            s.connect((host, port))
            s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            return s.recv(100)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        port = free_port()
        svc = MetricsService(f":{port}")
        await svc.start(Scheduler(site))
        try:
            assert svc.address == f"http://127.0.0.1:{port}/metrics"
            assert (await loop.run_in_executor(None, get, "127.0.0.1", port, socket.AF_INET)
                    ).startswith(b"HTTP/1.1 200")
            other = _non_loopback_ipv4()
            if other is not None:  # the machine has another address: it is not served
                with pytest.raises(OSError):
                    await loop.run_in_executor(None, get, other, port, socket.AF_INET, 5)
            body, ctype = svc.render()  # the exposition without HTTP
            assert ctype.startswith("text/plain") and b"rtupoll_device_up" in body
        finally:
            await svc.stop()
        port = free_port()
        svc = MetricsService(f"[::]:{port}")
        await svc.start(Scheduler(site))
        try:
            for host, family in (("127.0.0.1", socket.AF_INET), ("::1", socket.AF_INET6)):
                got = await loop.run_in_executor(None, get, host, port, family)
                assert got.startswith(b"HTTP/1.1 200"), host
        finally:
            await svc.stop()

    asyncio.run(main())


def test_the_docs_metrics_table_lists_every_family_the_collector_has() -> None:
    """docs/service.md's table against a scrape of a polling scheduler: every family
    that is not a field's is there, and every family it names is one rtupoll has (the
    gateway's three come from ``gateway.metrics``, with ``--serve``)."""
    import re

    from rtupoll.gateway import metrics as gateway_metrics

    bus, clock = simulated(["radar-level@4"])
    scheduler = Scheduler(from_specs("virtual", [("radar-level", 4)], check_serial=False),
                          open_bus=lambda _: bus, clock=clock)
    collector = SchedulerCollector(scheduler)
    asyncio.run(_cycles(scheduler, 1, collector))
    fields = {field_metric(f).name for f in scheduler.buses[0].devices[0].config.fields}
    counters = {m.name: m.type for m in collector.collect()}
    emitted = {n + ("_total" if t == "counter" else "") for n, t in counters.items()
               if not any(n == f or n.startswith(f"{f}_") for f in fields)}
    assert {"rtupoll_late_replies_total", "rtupoll_device_timeout_seconds"} <= emitted
    text = (Path(__file__).parents[2] / "docs" / "service.md").read_text()
    table = set(re.findall(r"^\| `(rtupoll_[a-z_]+)` \|", text, re.M))
    gateway = set(re.findall(r'"(rtupoll_gateway_[a-z_]+)"',
                             Path(gateway_metrics.__file__).read_text()))
    gateway = {n + "_total" if n.endswith("requests") else n for n in gateway}
    assert emitted <= table, sorted(emitted - table)
    assert table <= emitted | gateway, sorted(table - emitted - gateway)


def test_a_difference_in_kelvin_is_the_same_number_in_celsius() -> None:
    import dataclasses

    f = load_one("net-irnet-pro", []).field("temperature")
    assert field_metric(f).convert(296.67) == pytest.approx(23.52)
    offset = dataclasses.replace(f, name="temperature_offset")
    m = field_metric(offset)
    assert m.name == "rtupoll_temperature_offset_celsius" and m.convert(1.5) == 1.5
