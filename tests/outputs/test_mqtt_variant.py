"""A device whose generation lacks some fields (an IRNET-PRO on data structure 0 has no
calibration gas level): once it has said which it is, the Home Assistant discovery and
``bridge/info`` leave those fields out, so no entity is unknown for ever, and the state
says ``ok``; the real CLI, a real mosquitto, the simulator over TCP."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.outputs.test_mqtt_cli import Poll, polls_fixture  # noqa: F401

SITE = """\
buses:
  - name: line
    port: {port}
    baudrate: 9600
    devices:
      - {{name: gas, profile: net-irnet-pro, address: 1, interval: 0.2,
          fields: [temperature, concentration, calibration_gas_level]}}
mqtt:
  url: {url}/site
  gateway_id: g
"""
CONFIG = "homeassistant/device/rtupoll_g_gas/config"


def test_fields_the_generation_lacks_leave_the_discovery(
        broker: Broker, sim: Callable[..., SimulatedBus], polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    bus = sim("net-irnet-pro@1", tcp=True, options=["net-irnet-pro@1.variant=0"])
    site = tmp_path / "site.yaml"
    site.write_text(SITE.format(port=bus.port, url=broker.url))
    sub = broker.subscribe(CONFIG, "site/gas", "site/bridge/info")
    p = polls("-c", str(site), "--format", "json", "-o", str(tmp_path / "out.jsonl"))
    config = sub.wait(lambda m: m.topic == CONFIG and bool(m.payload)
                      and "calibration_gas_level" not in json.loads(m.payload)["cmps"])
    assert {"temperature", "concentration"} <= json.loads(config.payload)["cmps"].keys()
    info = sub.wait(lambda m: m.topic == "site/bridge/info" and "calibration_gas_level"
                    not in json.loads(m.payload)["devices"]["gas"]["fields"])
    assert "temperature" in json.loads(info.payload)["devices"]["gas"]["fields"]
    state = json.loads(sub.wait(lambda m: m.topic == "site/gas" and bool(m.payload)).payload)
    assert state["calibration_gas_level"] is None  # the key stays, null: not in structure 0
    assert state["_rtupoll"] == {"status": "ok", "error": None}
    assert p.stop() == 0, p.stderr
