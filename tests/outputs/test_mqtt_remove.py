"""``rtupoll poll --mqtt-remove-discovery`` against a real mosquitto: it clears what the
broker holds of this gateway (Home Assistant configs, bridge state and info, each
device's availability), counts it, and sends nothing where nothing is held: an empty
retained message on a config topic Home Assistant never saw makes it log a warning.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, Subscriber, broker_fixture  # noqa: F401  (the fixture)
from tests.outputs.test_mqtt_cli import (  # noqa: F401  (the fixtures)
    SITE,
    Poll,
    plant_fixture,
    polls_fixture,
    site_yaml,
)

GAS = "      - {{name: gas, profile: net-irnet-pro, address: 1, interval: 0.3}}\n"
OTHER = ("homeassistant/device/rtupoll_south_air/config",  # another gateway's device
         json.dumps({"dev": {"ids": ["rtupoll_south_air"], "name": "air"},
                     "o": {"name": "rtupoll", "sw": "0"}, "state_topic": "rtupoll/south/air",
                     "cmps": {}}))


def retain(broker: Broker, topic: str, payload: str) -> None:
    subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                    "-r", "-t", topic, "-m", payload], check=True, timeout=10)


def settled(broker: Broker, sub: Subscriber, after: int = 0) -> list[tuple[str, str]]:
    """Every message ``sub`` saw (from index ``after``) until a marker published now
    comes back (markers, ``Broker.retained``'s own probes, which can reach ``sub`` after
    the call, and the remover's own ``BASE/bridge/sync/...`` too, left out)."""
    # published until it comes back: one published before the broker has ``sub``'s
    # subscription (a fresh one, on a busy machine) reaches nobody
    for _ in range(120):
        subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q",
                        "1", "-t", "test/marker", "-m", "x"], check=True, timeout=10)
        if _came(sub, after):
            break
    sub.wait(lambda m: m.topic == "test/marker", after=after)
    return [(m.topic, m.payload) for m in sub.messages[after:]
            if m.topic != "test/marker" and not m.topic.startswith("tests/marker/")
            and "/bridge/sync/" not in m.topic]


def _came(sub: Subscriber, after: int) -> bool:
    """The marker arrived within half a second."""
    deadline = time.monotonic() + 0.5
    while time.monotonic() < deadline:
        if any(m.topic == "test/marker" for m in sub.messages[after:]):
            return True
        time.sleep(0.02)
    return False


def test_on_an_empty_broker_nothing_is_sent(broker: Broker, tmp_path: Path) -> None:
    site = site_yaml(tmp_path, "tcp://127.0.0.1:9", broker.url)
    sub = broker.subscribe("#")
    settled(broker, sub)  # heard: nothing the remover sends can go unseen
    before = len(sub.messages)
    done = rtupoll("poll", "-c", str(site), "--mqtt-remove-discovery")
    assert done.returncode == 0, done.stderr
    assert done.stderr.startswith("rtupoll: nothing to remove: ")
    assert "holds no Home Assistant discovery config of gateway 'plant' and no retained " \
        "topic under plant" in done.stderr
    assert settled(broker, sub, before) == []  # not one message: HA would log a warning for each


def test_on_a_populated_broker_exactly_this_gateways_topics_go(
        broker: Broker, plant: SimulatedBus, polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    first = polls("-c", str(site_yaml(tmp_path, plant.port, broker.url)), "--once")
    assert first.proc.wait(timeout=60) == 0, first.stderr
    retain(broker, *OTHER)
    retain(broker, "plant/notes", "kept: not a level of this gateway")
    # gas has left the site since: its config and availability are still this gateway's
    site = site_yaml(tmp_path, plant.port, broker.url, SITE.replace(GAS, ""))
    configs = [f"homeassistant/device/rtupoll_plant_{d}/config"
               for d in ("air", "gas", "curtain", "bus_plant")]
    topics = ["plant/bridge/state", "plant/bridge/info", "plant/air/availability",
              "plant/gas/availability", "plant/curtain/availability"]
    for t in configs + topics:
        assert broker.retained(t) is not None, t
    sub = broker.subscribe("#")
    settled(broker, sub)  # heard, and the retained messages, delivered on subscribing, first
    before = len(sub.messages)
    done = rtupoll("poll", "-c", str(site), "--mqtt-remove-discovery")
    assert done.returncode == 0, done.stderr
    assert "removed 4 Home Assistant discovery configs (homeassistant/device/...) and 5 " \
        "retained topics under plant (bridge state and info, availability)" in done.stderr
    seen = settled(broker, sub, before)
    assert sorted(seen) == sorted((t, "") for t in configs + topics)  # each once, emptied
    assert seen[-1] == ("plant/bridge/state", "")  # the bridge last
    for t in configs + topics:
        assert broker.retained(t) is None, t
    assert broker.retained(OTHER[0]) == OTHER[1]
    assert broker.retained("plant/notes") is not None
    # and again: nothing is left to remove, and nothing is sent
    n = len(sub.messages)
    again = rtupoll("poll", "-c", str(site), "--mqtt-remove-discovery")
    assert again.returncode == 0 and "nothing to remove" in again.stderr, again.stderr
    assert settled(broker, sub, n) == []
