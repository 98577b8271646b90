"""``rtupoll poll --mqtt`` end to end: the real CLI, a real mosquitto, mosquitto_sub/pub.

Each test starts its own broker on a free 127.0.0.1 port (``tests/brokers.py``) and
the simulator (in this process, over TCP, with pinned values; or ``--simulate``).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from cli_runner import rtupoll
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import (
    Broker,
    Msg,
    Subscriber,
    broker_fixture,  # noqa: F401  (the broker fixture)
    free_port,
)
from tests.cli.test_read_imports import imported, loaded

RTUPOLL = [sys.executable, "-m", "rtupoll"]


class Poll:
    """``rtupoll poll ARGS`` in the background; stderr kept in a file."""

    def __init__(self, tmp: Path, *args: str) -> None:
        self.args = " ".join(args)
        self.err_path = tmp / f"stderr-{time.monotonic_ns()}.txt"
        self._err = self.err_path.open("w")
        self.proc = rtupoll_popen([*RTUPOLL, "poll", *args], stdout=subprocess.DEVNULL,
                                     stderr=self._err, stdin=subprocess.DEVNULL)

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout=30)
        self._err.close()
        return code

    @property
    def stderr(self) -> str:
        return self.err_path.read_text()


@pytest.fixture(name="polls")
def polls_fixture(tmp_path: Path) -> Iterator[Callable[..., Poll]]:
    started: list[Poll] = []

    def start(*args: str) -> Poll:
        p = Poll(tmp_path, *args)
        started.append(p)
        return p

    yield start
    for p in started:
        if p.proc.poll() is None:
            p.stop(signal.SIGKILL)
        print(f"--- stderr of rtupoll poll {p.args}:\n{p.stderr}")


def publish(broker: Broker, topic: str, payload: str) -> None:
    subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                    "-t", topic, "-m", payload], check=True, timeout=10)


def payload(m: Msg) -> Any:
    return json.loads(m.payload)


def state(topic: str, check: Callable[[dict[str, Any]], bool] = lambda s: True
          ) -> Callable[[Msg], bool]:
    return lambda m: m.topic == topic and bool(m.payload) and check(payload(m))


SITE = """\
buses:
  - name: plant
    port: {port}
    baudrate: 9600
    devices:
      - {{name: air, profile: huiwen-aq, address: 3,
          fields: [co2, temperature, humidity, pm25, co2_level]}}
      - {{name: gas, profile: net-irnet-pro, address: 1, interval: 0.3}}
      - {{name: curtain, profile: banner-ez-array, address: 5, interval: 0.3,
          fields: [measurement_1, measurement_1_mode]}}
mqtt:
  url: {url}/plant
  gateway_id: plant
  qos: 1
  allow_writes: true
"""


@pytest.fixture(name="plant")
def plant_fixture(sim: Callable[..., SimulatedBus]) -> SimulatedBus:
    return sim("huiwen-aq@3", "net-irnet-pro@1", "banner-ez-array@5", tcp=True, tick=None,
               sets=["huiwen-aq@3.co2=800", "huiwen-aq@3.temperature=21",
                     "huiwen-aq@3.humidity=40", "huiwen-aq@3.pm25=12",
                     "huiwen-aq@3.co2_level=GOOD",
                     "net-irnet-pro@1.concentration=12.5",
                     "net-irnet-pro@1.warning=WARMUP_WARNING", "net-irnet-pro@1.error=NO_ERROR",
                     "banner-ez-array@5.measurement_1_mode=FBB"])


def site_yaml(tmp_path: Path, port: str, url: str, text: str = SITE) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(text.format(port=port, url=url))
    return path


def unique_ids(sub: Subscriber) -> set[str]:
    out = set()
    for m in sub.messages:
        if m.topic.startswith("homeassistant/device/rtupoll_plant_") and m.payload:
            out |= {c["unique_id"] for c in payload(m)["cmps"].values()}
    return out


def test_state_discovery_commands_and_a_clean_stop(
        broker: Broker, plant: SimulatedBus, polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    sub = broker.subscribe("plant/#", "homeassistant/#")
    site = site_yaml(tmp_path, plant.port, broker.url)
    run = polls("-c", str(site), "--format", "json")

    # state: the pinned values, numbers as numbers, enums by name, flags as lists
    air = payload(sub.wait(state("plant/air")))
    assert {k: air[k] for k in ("co2", "temperature", "humidity", "pm25")} == \
        {"co2": 800, "temperature": 21, "humidity": 40, "pm25": 12}
    assert air["co2_level"] == "GOOD" and air["last_seen"].endswith("Z")
    gas = payload(sub.wait(state("plant/gas")))
    assert (gas["concentration"], gas["warning"], gas["error"]) == \
        (12.5, ["WARMUP_WARNING"], "NO_ERROR")
    assert gas["_rtupoll"] == {"status": "ok", "error": None}
    assert sub.wait(lambda m: m.topic == "plant/air/availability").payload == "online"
    assert broker.retained("plant/bridge/state") == "online"

    # discovery, field by field
    cfg = payload(sub.wait(lambda m: m.topic == "homeassistant/device/rtupoll_plant_air/config"))
    assert cfg["dev"]["ids"] == ["rtupoll_plant_air"]
    assert (cfg["dev"]["name"], cfg["dev"]["mf"], cfg["dev"]["mdl_id"]) == \
        ("air", "Suzhou Huiwen Nanotechnology", "huiwen-aq")
    assert cfg["dev"]["via_device"] == "rtupoll_plant_bus_plant"
    assert cfg["state_topic"] == "plant/air"
    assert [a["topic"] for a in cfg["availability"]] == ["plant/bridge/state",
                                                         "plant/air/availability"]
    assert cfg["o"]["name"] == "rtupoll"
    expect = {  # field -> (component, unit, device class, state class)
        "co2": ("sensor", "ppm", "carbon_dioxide", "measurement"),
        "temperature": ("sensor", "°C", "temperature", "measurement"),
        "humidity": ("sensor", "%", "humidity", "measurement"),
        "pm25": ("sensor", "µg/m³", "pm25", "measurement"),
        "co2_level": ("sensor", None, "enum", None),
    }
    assert set(cfg["cmps"]) == set(expect) | {"_status", "_last_seen"}
    assert cfg["cmps"]["co2"]["name"] == "CO2 concentration"  # the profile's label
    for name, (p, unit, cls, sclass) in expect.items():
        c = cfg["cmps"][name]
        assert (c["p"], c.get("unit_of_measurement"), c.get("device_class"),
                c.get("state_class")) == (p, unit, cls, sclass), name
        assert c["unique_id"] == f"rtupoll_plant_air_{name}"
        assert name in c["value_template"]
    assert cfg["cmps"]["co2_level"]["options"][:2] == ["EXCELLENT", "GOOD"]
    gas_cfg = payload(sub.wait(
        lambda m: m.topic == "homeassistant/device/rtupoll_plant_gas/config"))
    flags = {k: v for k, v in gas_cfg["cmps"].items() if k.startswith("warning_")}
    assert len(flags) == 8 and all(v["p"] == "binary_sensor" for v in flags.values())
    assert gas_cfg["cmps"]["error"]["device_class"] == "enum"
    curtain = payload(sub.wait(
        lambda m: m.topic == "homeassistant/device/rtupoll_plant_curtain/config"))
    assert curtain["cmps"]["measurement_1_mode_set"]["p"] == "select"
    assert curtain["cmps"]["measurement_1_mode_set"]["command_topic"] == "plant/curtain/set"
    bus = payload(sub.wait(
        lambda m: m.topic == "homeassistant/device/rtupoll_plant_bus_plant/config"))
    assert bus["dev"]["ids"] == ["rtupoll_plant_bus_plant"]

    # a set that writes, reads back and reports
    publish(broker, "plant/curtain/set", '{"measurement_1_mode": "TBB"}')
    result = payload(sub.wait(lambda m: m.topic == "plant/curtain/set/result"))
    assert result == {"status": "ok", "exit_code": 0, "values": {"measurement_1_mode": "TBB"}}
    assert plant.get(5, "measurement_1_mode").value == "TBB"
    sub.wait(state("plant/curtain", lambda s: s["measurement_1_mode"] == "TBB"))

    # one that is refused, with the wording and exit code of 'rtupoll write'
    n = len(sub.messages)
    publish(broker, "plant/curtain/set", '{"measurement_1": 3}')
    refused = payload(sub.wait(lambda m: m.topic == "plant/curtain/set/result", after=n))
    cli = rtupoll("write", "-p", plant.port, "banner-ez-array@5", "measurement_1=3", "--yes")
    assert refused["status"] == "refused"
    assert refused["exit_code"] == cli.returncode == 8
    assert cli.stderr.strip() == f"rtupoll: {refused['error']}"

    # a get with a field list reads a field that is not polled
    publish(broker, "plant/curtain/get", '["emitter_channels"]')
    got = payload(sub.wait(lambda m: m.topic == "plant/curtain/get/result"))
    assert got["status"] == "ok"
    assert got["values"]["emitter_channels"] == plant.get(5, "emitter_channels").value

    # Home Assistant's birth message: the discovery is published again
    n = len(sub.messages)
    publish(broker, "homeassistant/status", "online")
    sub.wait(lambda m: m.topic == "homeassistant/device/rtupoll_plant_air/config", after=n)

    # SIGTERM: a clean stop leaves everything offline, retained
    assert run.stop(signal.SIGTERM) == 0, run.stderr
    assert broker.retained("plant/bridge/state") == "offline"
    assert broker.retained("plant/air/availability") == "offline"
    first = unique_ids(sub)
    assert "rtupoll_plant_air_co2" in first

    # a second run (--once) publishes the same unique ids
    sub2 = broker.subscribe("homeassistant/#")
    again = polls("-c", str(site), "--once", "--format", "json")
    assert again.proc.wait(timeout=30) == 0, again.stderr
    sub2.wait(lambda m: m.topic == "homeassistant/device/rtupoll_plant_curtain/config")
    assert unique_ids(sub2) == first


def test_last_will_says_offline_after_sigkill(broker: Broker, polls: Callable[..., Poll]
                                              ) -> None:
    sub = broker.subscribe("rtupoll/#")
    run = polls("--simulate", "--format", "json", "--fault", "3:dead", "--mqtt", broker.url,
                "--mqtt-id", "gw1")
    sub.wait(state("rtupoll/gw1/radar-level_2"))
    assert broker.retained("rtupoll/gw1/bridge/state") == "online"
    # a dead device: offline, and no value in its state, only why
    dead = payload(sub.wait(state("rtupoll/gw1/huiwen-aq_3")))
    assert dead["co2"] is None and dead["last_seen"] is None
    assert dead["_rtupoll"]["status"] == "failed"
    assert dead["_rtupoll"]["error"].startswith("timeout: ")
    assert broker.retained("rtupoll/gw1/huiwen-aq_3/availability") == "offline"
    assert broker.retained("rtupoll/gw1/radar-level_2/availability") == "online"
    n = len(sub.messages)
    run.stop(signal.SIGKILL)
    assert sub.wait(lambda m: m.topic == "rtupoll/gw1/bridge/state",
                    after=n).payload == "offline"
    assert broker.retained("rtupoll/gw1/bridge/state") == "offline"


def test_a_broker_restart_does_not_stop_polling(broker: Broker, polls: Callable[..., Poll],
                                                tmp_path: Path) -> None:
    out = tmp_path / "readings.jsonl"
    sub = broker.subscribe("rtupoll/#")
    # a scan every 0.3 s, not 1 s: the two scans without a broker come sooner
    run = polls("--simulate", "--interval", "0.3", "--format", "json", "-o", str(out),
                "--mqtt", broker.url, "--log-format", "text", "--mqtt-id", "gw1")
    sub.wait(state("rtupoll/gw1/huiwen-aq_3"))
    broker.stop()
    lines = len(out.read_text().splitlines())
    while len(out.read_text().splitlines()) < lines + 30:  # two more scans, broker gone
        time.sleep(0.1)
    broker.start()
    after = broker.subscribe("rtupoll/#", "homeassistant/#")
    after.wait(state("rtupoll/gw1/huiwen-aq_3"))
    # what the restarted broker had forgotten is published again, retained (discovery
    # first, then each device's availability, then its state)
    after.wait(lambda m: m.topic.endswith("rtupoll_gw1_huiwen-aq_3/config"))
    after.wait(lambda m: m.topic == "rtupoll/gw1/huiwen-aq_3/availability")
    assert broker.retained("rtupoll/gw1/huiwen-aq_3/availability") == "online"
    assert broker.retained("rtupoll/gw1/bridge/state") == "online"
    assert run.stop() == 0
    log = run.stderr
    assert log.count("lost the broker") == 1, log
    assert f"lost the broker {broker.url} (the connection was lost)" in log
    assert log.count("back on") == 1, log
    # no paho chatter, and no asyncio callback error (Python 3.13: add_writer on a closed
    # socket, see outputs/mqtt_client.py)
    assert "Traceback" not in log and "failed to receive" not in log
    assert "Exception in callback" not in log and "Bad file descriptor" not in log


def test_bad_credentials_are_one_line_and_exit_10(tmp_path: Path) -> None:
    with Broker(tmp_path / "auth", users={"gw": "right"}) as b:
        # --once: each ends by itself, so in this process (tests/cli_runner.py)
        done = rtupoll("poll", "--simulate", "--once", "--format", "json",
                       "--mqtt", f"mqtt://gw:wrong@127.0.0.1:{b.port}")
        assert done.returncode == 10
        assert done.stderr.splitlines() == [
            f"rtupoll: mqtt://127.0.0.1:{b.port}: the broker refused the credentials "
            "(user 'gw'): [code:135] Not authorized"]
        ok = rtupoll("poll", "--simulate", "--once", "--format", "json",
                     "--mqtt", f"mqtt://gw@127.0.0.1:{b.port}/x",
                     env={"RTUPOLL_MQTT_PASSWORD": "right"})
        assert ok.returncode == 0, ok.stderr
        assert b.retained("x/bridge/state", user="gw", password="right") == "offline"
        tls = rtupoll("poll", "--simulate", "--once", "--mqtt",
                      f"mqtts://gw:right@127.0.0.1:{b.port}")
        assert tls.returncode == 10
        assert tls.stderr.splitlines() == [
            f"rtupoll: mqtts://127.0.0.1:{b.port}: TLS handshake refused: the connection was "
            f"reset (is port {b.port} a TLS listener?)"]


def test_no_broker_is_one_line_and_exit_10() -> None:
    port = free_port()
    done = rtupoll("poll", "--simulate", "--once", "--mqtt", f"mqtt://127.0.0.1:{port}")
    assert done.returncode == 10
    assert done.stderr.splitlines() == [
        f"rtupoll: mqtt://127.0.0.1:{port}: connection refused (is the broker running on "
        f"port {port}?)"]


def test_discovery_follows_the_site_file_and_can_be_removed(
        broker: Broker, plant: SimulatedBus, polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    site = site_yaml(tmp_path, plant.port, broker.url)
    first = polls("-c", str(site), "--once")
    assert first.proc.wait(timeout=30) == 0, first.stderr
    gas = "homeassistant/device/rtupoll_plant_gas/config"
    assert broker.retained(gas) is not None
    # gas left the site file while the gateway was down: removed at start, others stay
    smaller = SITE.replace("      - {{name: gas, profile: net-irnet-pro, address: 1, "
                           "interval: 0.3}}\n", "")
    site = site_yaml(tmp_path, plant.port, broker.url, smaller)
    sub = broker.subscribe(gas)
    run = polls("-c", str(site))
    sub.wait(lambda m: m.topic == gas and m.payload == "")
    assert broker.retained(gas) is None
    air = "homeassistant/device/rtupoll_plant_air/config"
    assert broker.retained(air) is not None
    # SIGHUP with gas back in the file: announced again; without it: removed again
    site_yaml(tmp_path, plant.port, broker.url)
    n = len(sub.messages)
    run.proc.send_signal(signal.SIGHUP)
    back = sub.wait(lambda m: m.topic == gas and m.payload != "", after=n)
    assert payload(back)["dev"]["ids"] == ["rtupoll_plant_gas"]
    site_yaml(tmp_path, plant.port, broker.url, smaller)
    n = len(sub.messages)
    run.proc.send_signal(signal.SIGHUP)
    sub.wait(lambda m: m.topic == gas and m.payload == "", after=n)
    assert run.stop() == 0
    # --mqtt-remove-discovery: every config of this gateway goes, nothing is polled
    done = rtupoll("poll", "-c", str(site), "--mqtt-remove-discovery")
    assert done.returncode == 0, done.stderr
    assert "removed 3 Home Assistant discovery configs (homeassistant/device/...) and 4 " \
        "retained topics under plant" in done.stderr
    assert broker.retained(air) is None
    assert broker.retained("homeassistant/device/rtupoll_plant_bus_plant/config") is None
    assert broker.retained("plant/bridge/state") is None
    assert broker.retained("plant/air/availability") is None


def test_on_change_with_a_maximum_silence_get_and_field_topics(
        broker: Broker, plant: SimulatedBus, polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    text = SITE.replace("address: 3,", "address: 3, interval: 0.1,").replace(
        "  allow_writes: true\n",
        "  publish: on_change\n  max_silence: 86400\n  devices:\n"
        "    air: {{field_topics: true, max_silence: 1}}\n")
    site = site_yaml(tmp_path, plant.port, broker.url, text)
    out = tmp_path / "readings.jsonl"
    sub = broker.subscribe("plant/air", "plant/air/co2", "plant/gas")
    run = polls("-c", str(site), "--format", "json", "-o", str(out))
    first = sub.wait(state("plant/air"))
    assert sub.wait(lambda m: m.topic == "plant/air/co2").payload == "800"
    # the values are pinned: the next state comes only when max_silence has passed
    second = sub.wait(state("plant/air"), after=sub.messages.index(first) + 1)
    # by the gateway's own stamps (when each was read): a busy machine delivers the first
    # late as often as not, which shortens the gap the subscriber sees
    read_at = [datetime.fromisoformat(json.loads(m.payload)["last_seen"].replace("Z", "+00:00"))
               for m in (first, second)]
    assert (read_at[1] - read_at[0]).total_seconds() >= 0.9
    # gas would stay silent for a day: a get makes it publish its (unchanged) state
    gas = sub.wait(state("plant/gas"))
    publish(broker, "plant/gas/get", "")
    again = sub.wait(state("plant/gas"), after=sub.messages.index(gas) + 1)
    assert payload(again)["concentration"] == payload(gas)["concentration"] == 12.5
    assert run.stop() == 0
    scans = sum(1 for line in out.read_text().splitlines()
                if json.loads(line)["device"] == "air" and json.loads(line)["field"] == "co2")
    states = len(sub.on("plant/air"))
    assert states < scans / 3, (states, scans)


def test_tls_with_the_site_files_ca_and_a_refused_handshake(
        plant: SimulatedBus, tmp_path: Path) -> None:
    with Broker(tmp_path / "tls", tls=True) as b:
        url = f"mqtts://127.0.0.1:{b.tls_port}"
        site = site_yaml(tmp_path, plant.port, url, SITE.replace(
            "  allow_writes: true\n", f"  tls: {{{{ca: {b.ca}}}}}\n"))
        ok = rtupoll("poll", "-c", str(site), "--once", "--format", "json")
        assert ok.returncode == 0, ok.stderr
        assert b.retained("plant/air") is None  # the state is not retained by default
        assert b.retained("plant/bridge/state") == "offline"
        assert b.retained("homeassistant/device/rtupoll_plant_air/config") is not None
        # without the CA the server certificate cannot be verified: one line, exit 10
        bad = rtupoll("poll", "--simulate", "--once", "--mqtt", url)
        assert bad.returncode == 10
        (line,) = bad.stderr.splitlines()
        assert line.startswith(f"rtupoll: {url}: TLS handshake refused: ")
        assert "CERTIFICATE_VERIFY_FAILED" in line


def test_aiomqtt_is_imported_only_with_mqtt() -> None:
    modules = imported("poll", "--simulate", "--once", "--format", "json")
    assert "rtupoll.jobs.scheduler" in modules  # it did poll
    assert not loaded(modules, "aiomqtt") and not loaded(modules, "paho")
