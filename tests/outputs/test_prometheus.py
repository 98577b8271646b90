"""``poll --metrics`` scraped over HTTP and checked by Prometheus's own ``promtool``.

Every bundled profile polled on three simulated buses (with faults), the gateway
serving several clients (mbpoll ``-m tcp`` and raw Modbus TCP sockets, each a new
connection with a new ephemeral port), slow-interval fields (energy, ``interval: 60``)
present: every scrape piped into ``promtool check metrics`` must pass, and the names,
types, units and values must be what Prometheus practice asks.
"""

from __future__ import annotations

import contextlib
import math
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

from conftest import ANSWERED
from forked_cli import rtupoll_popen
from prometheus_client.parser import text_string_to_metric_families

from rtupoll.config.library import load_one
from rtupoll.outputs.metrics import field_metric
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port

PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
MBPOLL = shutil.which("mbpoll") or "/usr/bin/mbpoll"
PROFILES = sorted(p.stem for p in Path(__file__).parents[2].joinpath("profiles").glob("*.yaml"))


def promtool(text: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([PROMTOOL, "check", "metrics"], input=text, capture_output=True,
                          text=True, timeout=60)


def transactions(text: str) -> float:
    """The transactions of every bus, from a scrape."""
    return sum(s.value for f in text_string_to_metric_families(text)
               if f.name == "rtupoll_bus_transactions" for s in f.samples
               if s.name.endswith("_total"))


def scrape(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as r:
        assert r.status == 200
        body: bytes = r.read()
    return body.decode()


def register(profile: str) -> tuple[int, int]:
    """A register the profile's device answers: (function code 3 or 4, wire address)."""
    f = next(f for f in load_one(profile).fields if f.table.value in ("holding", "input"))
    return (3 if f.table.value == "holding" else 4), f.address


def raw_read(port: int, unit: int, function: int = 3, address: int = 0) -> bytes:
    """One Modbus TCP read of one register, on a connection of its own."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(struct.pack(">HHHBBHH", 1, 0, 6, unit, function, address, 1))
        return s.recv(260)


def test_promtool_passes_on_every_profile_the_gateway_and_slow_fields(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    assert len(PROFILES) >= 20
    # a line has one speed and parity: 9600 8N1 where a device can be set to it
    lines: dict[tuple[int, str], list[str]] = {}
    for p in PROFILES:
        serial = load_one(p).serial
        rate = 9600 if 9600 in (serial.baudrates or (serial.baudrate,)) else serial.baudrate
        lines.setdefault((rate, serial.parity), []).append(p)
    plain = lines.pop((9600, "N"))
    settings = [(9600, "N"), (9600, "N"), *lines]
    groups = [plain[0::2], plain[1::2], *lines.values()]
    faults = [["2:crc@20%"], ["3:exception@20%"], ["3:dead"]] + [[]] * (len(groups) - 3)
    buses = [sim(*(f"{p}@{a}" for a, p in enumerate(g, 1)), faults=f)
             for g, f in zip(groups, faults, strict=True)]
    irnet = next((b, a) for b, g in zip(buses, groups, strict=True)
                 for a, p in enumerate(g, 1) if p == "net-irnet-pro")
    irnet[0].set(irnet[1], "temperature", 296.67)  # 23.52 °C, not 23.52000000000004
    huiwen = next((b, a) for b, g in zip(buses, groups, strict=True)
                  for a, p in enumerate(g, 1) if p == "huiwen-aq")
    huiwen[0].set(huiwen[1], "pm25", 18)  # µg/m³: 1.8e-05 g/m³
    serve = [free_port(), free_port()]
    text = "buses:\n"
    for n, (bus, group) in enumerate(zip(buses, groups, strict=True)):
        rate, parity = settings[n]
        text += f"  - name: line{n}\n    port: {bus.port}\n    baudrate: {rate}\n" \
            f"    parity: {parity}\n"
        if n < 2:
            text += f"    serve: 127.0.0.1:{serve[n]}\n"
        text += "    devices:\n" + "".join(
            f"      - {{name: {p}, profile: {p}, address: {a}, interval: 0.5, "
            f"timeout: 1}}\n" for a, p in enumerate(group, 1))
    site = tmp_path / "site.yaml"
    site.write_text(text, encoding="utf-8")
    metrics = free_port()
    err = (tmp_path / "stderr").open("w")
    proc = rtupoll_popen(
        [sys.executable, "-m", "rtupoll", "poll", "-c", str(site), "--format", "json",
         "-o", str(tmp_path / "readings.jsonl"), "--metrics", f":{metrics}"],
        stdout=subprocess.DEVNULL, stderr=err)
    try:
        families = {}
        deadline = time.monotonic() + 90  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                families = {f.name: f for f in text_string_to_metric_families(scrape(metrics))}
                up = families.get("rtupoll_device_up")
                if up is not None and sum(s.value for s in up.samples) >= len(PROFILES) - 1:
                    break
            time.sleep(0.2)
        # clients: mbpoll (one connection per run) and raw sockets, on both gateways;
        # mbpoll's timeout 5 s: line0 carries half the 9600 8N1 profiles polled every
        # 0.5 s (Growatt's 850 ms idle gaps among them), a gateway request waits its turn
        fc, address = register(groups[0][0])
        for n in range(3):
            # (ANSWERED: the reply ends the wait; the gateway's turn may come after a
            # dead unit's timeout on a line this full)
            got = subprocess.run([MBPOLL, "-m", "tcp", "-p", str(serve[0]), "-1", "-o",
                                  f"{ANSWERED:g}",
                                  "-a", "1", "-t", "4" if fc == 3 else "3", "-0",
                                  "-r", str(address), "-c", "1", "127.0.0.1"],
                                 capture_output=True, text=True, timeout=30)
            assert got.returncode == 0, got.stdout + got.stderr
            unit = 4 + n  # not line1's faulty unit 3
            reply = raw_read(serve[1], unit, *register(groups[1][unit - 1]))
            assert reply[7] in (3, 4) and len(reply) == 11, reply.hex()
        raw_read(serve[0], 200)  # a unit nobody has: timeout, counted too
        scrapes = [scrape(metrics)]
        # a second scrape once every bus has gone on (a scan's worth of transactions
        # more), not after a fixed second
        first = transactions(scrapes[0])
        deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            scrapes[1:] = [scrape(metrics)]
            if transactions(scrapes[1]) >= first + len(PROFILES):
                break
            time.sleep(0.1)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    log = (tmp_path / "stderr").read_text()
    # --metrics :PORT listens on loopback only, as --serve does
    assert f"serving metrics on http://127.0.0.1:{metrics}/metrics" in log

    for text in scrapes:
        checked = promtool(text)
        assert checked.returncode == 0, checked.stdout + checked.stderr
        assert checked.stdout == "" and checked.stderr == ""
    text = scrapes[-1]
    families = {f.name: f for f in text_string_to_metric_families(text)}

    # every profile is there, and every device that lives answered
    info = {s.labels["profile"] for s in families["rtupoll_device_info"].samples}
    assert info == set(PROFILES)
    # no quantile label anywhere: a summary or histogram carries them, never a gauge
    assert not [f.name for f in families.values() for s in f.samples
                if "quantile" in s.labels and f.type != "summary"]
    # the gateway: clients by host, never HOST:PORT (bounded series)
    requests = families["rtupoll_gateway_requests"]
    assert requests.type == "counter"
    assert {s.labels["client"] for s in requests.samples} == {"127.0.0.1"}
    assert len(requests.samples) == 2 * 6  # two gateways, one host, six outcomes
    answered = {s.labels["bus"]: s.value for s in requests.samples
                if s.labels["outcome"] == "answered"}
    assert answered == {"line0": 3, "line1": 3}
    timeouts = [s.value for s in requests.samples if s.labels["outcome"] == "timeout"
                and s.labels["bus"] == "line0"]
    assert timeouts == [1]
    waits = families["rtupoll_gateway_queue_wait_seconds"]
    assert waits.type == "histogram"
    counts = {s.labels["bus"]: s.value for s in waits.samples
              if s.name.endswith("_count")}
    assert counts == {"line0": 4, "line1": 3}
    # base units; energy totals are counters
    assert not [n for n in families if "micro" in n or "kilo" in n]
    pm25 = families["rtupoll_pm25_grams_per_cubic_meter"]
    assert [s.value for s in pm25.samples] == [1.8e-05]
    energy = families["rtupoll_import_active_energy_joules"]  # slow: interval 60
    assert energy.type == "counter" and energy.samples
    assert all(s.name.endswith("_total") for s in energy.samples)
    counters = {f.name for f in families.values() if f.type == "counter"}
    for p in PROFILES:
        for fld in load_one(p).fields:
            if fld.counter and fld.poll.value == "default":
                # (its family's name: a unit the name spells is dropped, as documented)
                assert field_metric(fld).name in counters, (p, fld.name)
    # one HELP per family, naming the field and the family's unit, no profile's own unit
    temperature = families["rtupoll_temperature_celsius"]
    assert temperature.documentation == "Field temperature, in celsius"
    assert {s.labels["device"] for s in temperature.samples} >= {
        "net-irnet-pro", "huiwen-aq", "xy-md02"}
    # no float noise: K -> °C is 23.52; field values carry at most 12 significant digits
    assert [s.value for s in temperature.samples if s.labels["device"] == "net-irnet-pro"
            ] == [23.52]
    field_values = [s for f in families.values() for s in f.samples
                    if f.type in ("gauge", "counter") and not s.name.startswith(
                        ("rtupoll_bus_", "rtupoll_device_", "rtupoll_last_", "rtupoll_gateway"))]
    assert len(field_values) > 200
    noisy = [(s.name, s.value) for s in field_values if math.isfinite(s.value)
             and len(re.sub(r"[-.]|e.*", "", repr(s.value)).strip("0")) > 12]
    assert not noisy, noisy[:5]


def test_gateway_counters_per_host_survive_connections_leaving_the_list() -> None:
    """More connections than the gateway keeps (32), one of them open all along: the
    host's counters count every request, never go down, and stay one series each."""
    from rtupoll.gateway.metrics import host_of
    from rtupoll.gateway.server import KEEP_CLIENTS

    assert host_of("[::1]:40000") == "::1" and host_of("10.0.0.7:502") == "10.0.0.7"
    metrics, serve = free_port(), free_port()
    proc = rtupoll_popen(
        [sys.executable, "-m", "rtupoll", "poll", "--simulate", "huiwen-aq@3", "--format",
         "json", "-o", "/dev/null", "--serve", f"127.0.0.1:{serve}", "--metrics",
         f"127.0.0.1:{metrics}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    fc, address = register("huiwen-aq")
    request = struct.pack(">HHHBBHH", 1, 0, 6, 3, fc, address, 1)

    def answered(text: str) -> float:
        (fam,) = [f for f in text_string_to_metric_families(text)
                  if f.name == "rtupoll_gateway_requests"]
        assert len(fam.samples) == 6, fam.samples  # one host: one series per outcome
        return sum(s.value for s in fam.samples if s.labels["outcome"] == "answered")

    def connected(text: str) -> float:
        return sum(s.value for f in text_string_to_metric_families(text)
                   if f.name == "rtupoll_gateway_clients" for s in f.samples)

    try:
        deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                raw_read(serve, 3, fc, address)
                break
            time.sleep(0.2)
        while time.monotonic() < deadline:  # (the metrics port may open after the gateway's)
            with contextlib.suppress(OSError):
                scrape(metrics)
                break
            time.sleep(0.2)
        seen = [answered(scrape(metrics))]
        with socket.create_connection(("127.0.0.1", serve), timeout=10) as long:
            long.sendall(request)
            assert len(long.recv(260)) == 11
            for n in range(KEEP_CLIENTS + 8):
                assert len(raw_read(serve, 3, fc, address)) == 11
                if n % 10 == 0:
                    seen.append(answered(scrape(metrics)))
            long.sendall(request)  # out of the gateway's list by now, still counting
            assert len(long.recv(260)) == 11
            seen.append(answered(scrape(metrics)))
        # once the gateway has seen the closes (no client connected), not after 0.5 s
        deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
        while (text := scrape(metrics)) and connected(text) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert connected(text) == 0, text
        seen.append(answered(text))
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    assert seen == sorted(seen), seen  # a counter never goes down
    assert seen[-1] == 1 + 2 + KEEP_CLIENTS + 8
