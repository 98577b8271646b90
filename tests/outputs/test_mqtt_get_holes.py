"""MQTT ``get`` over an undocumented hole gives what ``rtupoll read`` gives (and what a
``poll`` cycle reads): the real CLI, a real mosquitto, the simulator over TCP with the
Huiwen module's ``hole=`` fault (input 30011, inside the gap the profile lets the planner
bridge), every request on the wire seen through the simulator's ``on_wire``."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.config.site import from_specs
from rtupoll.errors import RtupollError
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.outputs import mqtt_commands as cmd
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadRequest, parse_request
from rtupoll.sim.device import SimDeviceConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.server import WireFrame
from rtupoll.sim.virtual import VirtualBus, VirtualClock
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.outputs.test_mqtt_cli import Poll, payload, polls_fixture, publish  # noqa: F401

SIX = ["pm25", "tvoc", "hcho", "co2", "temperature", "humidity"]  # input 30006+8, over 30011
SITE = """\
buses:
  - name: line
    port: {port}
    baudrate: 9600
    devices:
      - {{name: air, profile: huiwen-aq, address: 3, interval: 3600, fields: [co2_level]}}
mqtt:
  url: {url}/site
  gateway_id: g
"""


class Wire:
    """The requests (function, address, count) and exception replies on the simulated line."""

    def __init__(self) -> None:
        self.frames: list[WireFrame] = []
        self._lock = threading.Lock()

    def __call__(self, frame: WireFrame) -> None:  # the simulator's thread
        with self._lock:
            self.frames.append(frame)

    def mark(self) -> int:
        with self._lock:
            return len(self.frames)

    def reads(self, since: int) -> list[tuple[int, int, int]]:
        with self._lock:
            frames = self.frames[since:]
        out = []
        for f in frames:
            if f.direction == "in":
                req = parse_request(f.data)
                assert isinstance(req, ReadRequest)
                out.append((req.function, req.address, req.count))
        return out

    def refusals(self, since: int) -> int:
        with self._lock:
            return sum(1 for f in self.frames[since:] if f.direction == "out"
                       and len(f.data) > 2 and f.data[1] & 0x80)


def test_get_over_a_hole_reads_what_read_reads_and_the_poller_learns_the_hole(
        broker: Broker, sim: Callable[..., SimulatedBus], polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    wire = Wire()
    line = sim("huiwen-aq@3", tcp=True, tick=None, faults=["3:hole=30011"], on_wire=wire,
               sets=["huiwen-aq@3.pm25=12", "huiwen-aq@3.tvoc=0.25", "huiwen-aq@3.hcho=0.02",
                     "huiwen-aq@3.co2=800", "huiwen-aq@3.temperature=21",
                     "huiwen-aq@3.humidity=40"])
    read = rtupoll("read", "-p", line.port, "--format", "json", "huiwen-aq@3", *SIX)
    assert read.returncode == 0, read.stderr
    by_read = wire.reads(0)
    assert wire.refusals(0) == 3  # the block over the hole, the gap, its register 30011
    values = {r["field"]: r["value"] for r in map(json.loads, read.stdout.splitlines())}
    assert values == {"pm25": 12, "tvoc": 0.25, "hcho": 0.02, "co2": 800, "temperature": 21,
                      "humidity": 40}
    # a poll cycle of the same fields, nothing learned: the same requests, the same values
    asked = wire.mark()
    cycle = rtupoll("poll", "-p", line.port, "--once", "--format", "json", "--fields",
                    ",".join(SIX), "huiwen-aq@3")
    assert cycle.returncode == 0, cycle.stderr
    assert wire.reads(asked) == by_read
    assert {r["field"]: r["value"] for r in map(json.loads, cycle.stdout.splitlines())} == \
        values

    site = tmp_path / "site.yaml"
    site.write_text(SITE.format(port=line.port, url=broker.url))
    sub = broker.subscribe("site/#")
    p = polls("-c", str(site), "--format", "json", "-o", str(tmp_path / "out.jsonl"))
    sub.wait(lambda m: m.topic == "site/air" and bool(m.payload))  # its one cycle: co2_level

    # the poller never read the block over the hole: the get finds it, as read did
    n, asked = len(sub.messages), wire.mark()
    publish(broker, "site/air/get", json.dumps(SIX))
    first = payload(sub.wait(lambda m: m.topic == "site/air/get/result", after=n))
    assert first == {"status": "ok", "exit_code": 0, "values": values}
    assert wire.reads(asked) == by_read
    # and teaches the poller: the next get (and cycle) plans around it, no exception 02
    n, asked = len(sub.messages), wire.mark()
    publish(broker, "site/air/get", json.dumps(SIX))
    second = payload(sub.wait(lambda m: m.topic == "site/air/get/result", after=n))
    assert second == first
    assert wire.reads(asked) == [(4, 30006, 4), (4, 30012, 2)] and wire.refusals(asked) == 0
    assert p.stop() == 0, p.stderr


def test_a_field_the_device_refuses_fails_the_get_as_read_fails_with_the_others_read(
        sim: Callable[..., SimulatedBus]) -> None:
    """pm25's own register refused: ``read`` prints the other five and exits 5; the get's
    result is that exit code and line, with the values read printed (pm25 null)."""
    pinned = {"tvoc": 0.25, "hcho": 0.02, "co2": 800, "temperature": 21, "humidity": 40}
    line = sim("huiwen-aq@3", tick=None, faults=["3:hole=30006"],
               sets=[f"huiwen-aq@3.{n}={v}" for n, v in pinned.items()])
    read = rtupoll("read", "-p", line.port, "--format", "json", "huiwen-aq@3", *SIX)
    assert read.returncode == 5
    shown = {r["field"]: r["value"] for r in map(json.loads, read.stdout.splitlines())}
    assert shown == {"pm25": None, **pinned}

    config = from_specs(line.port, [("huiwen-aq", 3)], baudrate=9600).buses[0]
    engine = Engine([SimDeviceConfig(load_one("huiwen-aq"), 3,
                                     faults=(parse_fault("3:hole=30006"),))], tick=None)
    for name, value in pinned.items():
        engine.device(3).pin(name, value)
    clock = VirtualClock()
    bus = VirtualBus(engine, Framing(9600), clock=clock, sleep=clock.sleep)
    dev = BusPoller(config, bus, backoff=Backoff(), clock=clock, wall=clock).devices[0]
    profile = dev.config.profile
    done: dict[str, Any] = {}
    with pytest.raises(RtupollError) as info:
        asyncio.run(cmd.apply_get(bus, dev, [profile.field(n) for n in SIX], done))
    result = cmd.failed(info.value, done)
    assert result == {"status": "exception", "exit_code": 5, "error": result["error"],
                      "values": shown}
    assert read.stderr.strip() == f"rtupoll: {result['error']}"
    assert result["error"].startswith("pm25: ")
