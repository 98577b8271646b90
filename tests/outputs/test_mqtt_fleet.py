"""Several gateways on one broker, and commands that carry anything: the real CLI, a
real mosquitto (``tests/brokers.py``), the simulator."""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.outputs.test_mqtt_cli import (  # noqa: F401  (fixtures: plant, polls)
    Poll,
    plant_fixture,
    polls_fixture,
    publish,
    site_yaml,
    state,
)


def test_two_gateways_share_a_broker_and_a_base_is_held_by_one(
        broker: Broker, polls: Callable[..., Poll]) -> None:
    sub = broker.subscribe("#")
    north = polls("--simulate", "--format", "json", "--mqtt", broker.url, "--mqtt-id", "north")
    sub.wait(state("rtupoll/north/huiwen-aq_3"))
    info = json.loads(sub.wait(lambda m: m.topic == "rtupoll/north/bridge/info").payload)
    assert (info["gateway"], info["base"]) == ("north", "rtupoll/north")
    assert info["devices"]["huiwen-aq_3"]["fields"]["co2"]["label"] == "CO2 concentration"
    assert broker.retained("rtupoll/north/bridge/info") is not None
    # a second gateway with its own id: its own topics and Home Assistant ids
    # (the --once runs end by themselves: in this process, tests/cli_runner.py)
    south = rtupoll("poll", "--simulate", "--once", "--format", "json",
                    "--mqtt", broker.url, "--mqtt-id", "south")
    assert south.returncode == 0, south.stderr
    assert broker.retained("homeassistant/device/rtupoll_south_huiwen-aq_3/config")
    assert broker.retained("homeassistant/device/rtupoll_north_huiwen-aq_3/config")
    # a gateway that would publish under north's base: refused, one line, exit 10
    clash = rtupoll("poll", "--simulate", "--once", "--format", "json",
                    "--mqtt", f"{broker.url}/rtupoll/north", "--mqtt-id", "south")
    assert clash.returncode == 10
    assert clash.stderr.splitlines() == [
        f"rtupoll: mqtt://127.0.0.1:{broker.port}: gateway 'north' is online under the base "
        "topic 'rtupoll/north'; give this one ('south') its own (--mqtt-id, or a base in the "
        "URL), or if 'north' is gone for good: mosquitto_pub -r -n -t "
        "rtupoll/north/bridge/state"]
    assert broker.retained("rtupoll/north/bridge/state") == "online"  # north untouched
    # once north has stopped, its base is free
    assert north.stop(signal.SIGTERM) == 0
    again = rtupoll("poll", "--simulate", "--once", "--format", "json",
                    "--mqtt", f"{broker.url}/rtupoll/north", "--mqtt-id", "south")
    assert again.returncode == 0, again.stderr
    assert json.loads(broker.retained("rtupoll/north/bridge/info") or "{}")["gateway"] == "south"


def test_every_command_gets_one_result_whatever_it_carries(
        broker: Broker, plant: SimulatedBus, polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    sub = broker.subscribe("plant/#")
    site = site_yaml(tmp_path, plant.port, broker.url)
    run = polls("-c", str(site), "--format", "json", "--log-format", "text")
    sub.wait(state("plant/gas"))
    commands = [
        ("set", '{"calibration_gas_level": 1e39}', "outside what the field can hold"),
        ("set", '{"calibration_gas_level": -1e39}', "outside what the field can hold"),
        ("set", "[" * 100_000, "at most 16384"),
        ("get", "[" * 100_000, "at most 16384"),
        ("set", "[" * 2000 + "]" * 2000, "nests deeper"),
        ("get", "{" * 5000, "nests deeper"),
        ("set", '{"calibration_gas_level": "1_0"}', "is not a number"),
        ("set", '{"calibration_gas_level": "\uff11"}', "is not a number"),
        ("set", '{"calibration_gas_level": true}', "is not a value for it"),
        ("set", '{"calibration_gas_level": "1e1"}', "is not a number"),
        ("set", '{"calibration_gas_level": 5, "calibration_gas_level": 50}',
         'the key "calibration_gas_level" twice'),
        ("set", "not json", "not JSON"),
        ("set", '{"calibration_gas_level": 1' + "0" * 5000 + "}", "not JSON"),
    ]
    for n, (verb, body, why) in enumerate(commands, 1):
        before = len(sub.messages)
        publish(broker, f"plant/gas/{verb}", body)
        result = json.loads(sub.wait(lambda m, verb=verb: m.topic == f"plant/gas/{verb}/result",
                                     after=before).payload)
        assert result["exit_code"] != 0 and why in result["error"], (body[:40], result)
        results = [m for m in sub.messages if m.topic.endswith("/result")]
        assert len(results) == n, [m.payload[:80] for m in results]  # one each, no more
    assert run.stop() == 0
    assert "Traceback" not in run.stderr and "Error" not in run.stderr.replace("error", "")
    for why in ('"1e1" is not a number', "twice"):  # each refusal one log line too
        assert len([x for x in run.stderr.splitlines() if why in x]) == 1, run.stderr


def test_a_retained_command_is_not_run(broker: Broker, plant: SimulatedBus,
                                       polls: Callable[..., Poll], tmp_path: Path) -> None:
    # left on the broker by someone's 'mosquitto_pub -r' long ago
    subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                    "-r", "-t", "plant/curtain/set", "-m", '{"measurement_1_mode": "TBB"}'],
                   check=True, timeout=10)
    sub = broker.subscribe("plant/#")
    site = site_yaml(tmp_path, plant.port, broker.url)
    run = polls("-c", str(site), "--format", "json", "--log-format", "text")
    first = sub.wait(state("plant/curtain"))
    for _ in range(3):  # a few scans later: never written
        sub.wait(state("plant/curtain"), after=sub.messages.index(first) + 1)
    assert plant.get(5, "measurement_1_mode").value == "FBB"
    assert not sub.on("plant/curtain/set/result")
    # a command sent now is run
    publish(broker, "plant/curtain/set", '{"measurement_1_mode": "LBB"}')
    sub.wait(lambda m: m.topic == "plant/curtain/set/result")
    assert plant.get(5, "measurement_1_mode").value == "LBB"
    assert run.stop() == 0
    said = [line for line in run.stderr.splitlines() if "retained command" in line]
    assert len(said) == 1 and "plant/curtain/set" in said[0], run.stderr
