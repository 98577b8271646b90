"""Home Assistant's view: the discovery rendered against the state messages, as HA reads them.

A multi-device run of the real CLI on the simulator, with a block that fails (an
exception reply), a dead device, fields on a slow interval (the SDM120's and the
EM24's energy, ``interval: 60``), undocumented enum codes (the IRNET's ``error`` enum, a
Banner mode behind a select), a sentinel (the EM24's voltage L2 at OVERFLOW) and
writable numbers, publishing to a real mosquitto. Every
``value_template`` and ``json_attributes_template`` of every discovered entity is
rendered with Jinja2 the way Home Assistant renders it (``value`` the payload,
``value_json`` the parsed JSON, in a sandboxed environment), against every state
message, with ``StrictUndefined``: a key the message lacks is an error here, where HA
would log a warning on every message. Then what HA would do with the result: an enum
sensor's or a select's option must be one of its ``options`` (or ``None``, HA's "no
value"), a number within its box, a binary sensor ON/OFF, a measurement a number.
"""

from __future__ import annotations

import json
import math
import signal
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import jinja2
import pytest
from jinja2.sandbox import ImmutableSandboxedEnvironment

from rtupoll.config.library import load_one
from rtupoll.model.codec import DataType, value_range
from rtupoll.outputs import homeassistant as ha
from rtupoll.sim.runner import simulated_bus
from tests.brokers import Broker, Subscriber, have_mosquitto
from tests.outputs.test_mqtt_cli import Poll

SITE = """\
buses:
  - name: plant
    port: {port}
    baudrate: 9600
    devices:
      - {{name: air, profile: huiwen-aq, address: 3, interval: 0.3}}
      - {{name: gas, profile: net-irnet-pro, address: 1, interval: 0.3,
          fields: [temperature, concentration, error, warning, calibration_gas_level]}}
      - {{name: curtain, profile: banner-ez-array, address: 5, interval: 0.3,
          fields: [measurement_1, measurement_1_mode, error_code, outputs]}}
      - {{name: meter, profile: eastron-sdm120, address: 7, interval: 0.3}}
      - {{name: room, profile: xy-md02, address: 8, interval: 0.3,
          fields: [temperature, humidity, temperature_correction]}}
      - {{name: tank, profile: radar-level, address: 2, interval: 0.3}}
      - {{name: grid, profile: carlo-gavazzi-em24, address: 9, interval: 0.3}}
mqtt:
  url: {url}/plant
  gateway_id: north
  allow_writes: true
"""
DEVICES = ("air", "gas", "curtain", "meter", "room", "tank", "grid")


def environment() -> Any:
    """Jinja2 as Home Assistant sets it up for MQTT templates (sandboxed), but strict
    about undefined names; ``tojson`` is Jinja2's own, as in HA."""
    return ImmutableSandboxedEnvironment(undefined=jinja2.StrictUndefined)


def render(env: Any, template: str, payload: str) -> str:
    return str(env.from_string(template).render(value=payload, value_json=json.loads(payload)))


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory
        ) -> Iterator[tuple[dict[str, Any], dict[str, list[str]]]]:
    """(discovery config by device, state payloads by device) of a run with faults: one
    run that the tests of this module read, none of them changes."""
    if not have_mosquitto():
        pytest.skip("mosquitto is not installed (scripts/test installs it)")
    tmp_path = tmp_path_factory.mktemp("ha-run")
    broker = Broker(tmp_path / "broker").start()
    try:
        with simulated_bus(
                ["huiwen-aq@3", "net-irnet-pro@1", "banner-ez-array@5", "eastron-sdm120@7",
                 "xy-md02@8", "radar-level@2", "carlo-gavazzi-em24@9"], tcp=True,
                faults=["3:hole=0x759A", "2:dead"],  # the Huiwen's PM2.5 failure code; the radar
                sets=["net-irnet-pro@1.error=48",  # undocumented codes
                      "banner-ez-array@5.measurement_1_mode=200"]) as bus:
            bus.set(9, "voltage_l2", "OVERFLOW")  # its profile's sentinel: no value
            site = tmp_path / "site.yaml"
            site.write_text(SITE.format(port=bus.port, url=broker.url))
            sub = broker.subscribe("plant/#", "homeassistant/#")
            p = Poll(tmp_path, "-c", str(site), "--format", "json", "-o",
                     str(tmp_path / "out.jsonl"))
            try:
                configs, states = collect(sub, p)
            finally:
                if p.proc.poll() is None:
                    p.stop(signal.SIGKILL)
        yield configs, states
    finally:
        broker.close()


# state messages to collect of each device: a few scans (the SDM120's energy is read in
# the first only); of the dead radar two: its first failed scan, and one after its first
# backoff step (1 s), the same message again. Each further one is the same message after
# a backoff twice as long (2 s, 4 s ...): it proves nothing the second does not.
SCANS = {name: 2 if name == "tank" else 4 for name in DEVICES}


def collect(sub: Subscriber, p: Poll) -> tuple[dict[str, Any], dict[str, list[str]]]:
    for name in DEVICES:
        for n in range(SCANS[name]):
            sub.wait(lambda m, name=name, n=n: m.topic == f"plant/{name}"
                     and len(sub.on(f"plant/{name}")) > n)
    for name in DEVICES:
        sub.wait(lambda m, name=name: m.topic == f"homeassistant/device/rtupoll_north_{name}"
                 "/config")
    assert p.stop(signal.SIGTERM) == 0, p.stderr
    configs = {name: json.loads(sub.on(f"homeassistant/device/rtupoll_north_{name}/config")[-1]
                                .payload) for name in DEVICES}
    states = {name: [m.payload for m in sub.on(f"plant/{name}") if m.payload]
              for name in DEVICES}
    return configs, states


def test_every_template_renders_against_every_state_message(
        run: tuple[dict[str, Any], dict[str, list[str]]]) -> None:
    configs, states = run
    env = environment()
    seen_unknown_enum = seen_partial = seen_failed = seen_null_select = False
    for name in DEVICES:
        cfg = configs[name]
        assert len(states[name]) >= SCANS[name]
        for payload in states[name]:
            status = json.loads(payload)["_rtupoll"]["status"]
            seen_partial |= status == "partial"
            seen_failed |= status == "failed"
            for cid, c in cfg["cmps"].items():
                where = f"{name}.{cid} on {payload[:300]}"
                if c.get("state_topic", cfg["state_topic"]) != cfg["state_topic"]:
                    continue  # the bus's gateway sensor reads bridge/state
                try:
                    got = render(env, c["value_template"], payload)
                    if "json_attributes_template" in c:
                        attrs = json.loads(render(env, c["json_attributes_template"], payload))
                        assert isinstance(attrs, dict), where
                except jinja2.UndefinedError as exc:
                    pytest.fail(f"{where}: {exc}")
                check(c, got, where)
                if c["p"] == "select" and got == "None":
                    seen_null_select = True
                if c.get("device_class") == "enum" and cid == "error":
                    seen_unknown_enum |= json.loads(payload)["error"] == "unknown (48)"
    # the run had what the test is about
    assert seen_unknown_enum and seen_partial and seen_failed and seen_null_select


def check(c: dict[str, Any], got: str, where: str) -> None:
    """What Home Assistant does with a rendered value: accept it, or log and drop it."""
    if got == "None":  # HA's PAYLOAD_NONE: the entity has no value (unknown)
        return
    if c["p"] == "select" or c.get("device_class") == "enum":
        assert got in c["options"], f"{where}: {got!r} is not one of {c['options']}"
    elif c["p"] == "number":
        value = float(got)
        assert c["min"] <= value <= c["max"], f"{where}: {value} outside {c['min']}..{c['max']}"
    elif c["p"] == "binary_sensor":
        assert got in ("ON", "OFF"), where
    elif c.get("device_class") == "timestamp":
        datetime.fromisoformat(got.replace("Z", "+00:00"))
    elif "state_class" in c:
        assert math.isfinite(float(got)), where


def test_every_discovered_key_is_in_every_state_message(
        run: tuple[dict[str, Any], dict[str, list[str]]]) -> None:
    configs, states = run
    for name in DEVICES:
        fields = {f for f in configs[name]["cmps"] if not f.startswith("_")}
        keys = [set(json.loads(p)) for p in states[name]]
        for k in keys:
            assert {"last_seen", "_rtupoll"} <= k
            missing = {f for f in fields if f.split("_set")[0] not in k
                       and not any(f.startswith(f"{key}_") for key in k)}
            assert not missing, (name, missing)
    # the slow fields keep their last value between their reads
    meter = [json.loads(p) for p in states["meter"]]
    assert all(m["import_active_energy"] is not None for m in meter)
    assert len({m["import_active_energy"] for m in meter}) == 1  # read once (interval 60)
    # a refused register (the PM2.5 failure code) leaves every other value, its block's
    # included (the block is split until the refused field is found), and says why
    # under _rtupoll
    air = json.loads(states["air"][-1])
    assert air["co2"] is not None and air["co2_failure"] is not None
    assert air["pm25_failure"] is None
    assert air["_rtupoll"]["status"] == "partial"
    assert air["_rtupoll"]["error"].startswith("exception: ")
    gas = json.loads(states["gas"][-1])
    assert gas["error"] == "unknown (48)"  # the field's own value, never rtupoll's status


def test_a_sentinel_is_unknown_in_home_assistant_and_named_in_the_status_attributes(
        run: tuple[dict[str, Any], dict[str, list[str]]]) -> None:
    """The EM24's voltage L2 at its sentinel: the sensor renders None (HA's unknown, not
    a number), as every other null; the *Polling status* is partial, and its attributes
    (``_rtupoll``) name the sentinel, which the fleet page shows."""
    configs, states = run
    env = environment()
    cmps = configs["grid"]["cmps"]
    for payload in states["grid"]:
        assert json.loads(payload)["voltage_l2"] is None
        assert render(env, cmps["voltage_l2"]["value_template"], payload) == "None"
        assert float(render(env, cmps["voltage_l1"]["value_template"], payload)) > 200
        assert render(env, cmps["_status"]["value_template"], payload) == "partial"
        attrs = json.loads(render(env, cmps["_status"]["json_attributes_template"], payload))
        assert attrs["sentinels"] == {"voltage_l2": "OVERFLOW"}
        assert attrs["error"] == "no value: voltage_l2 is OVERFLOW"


def test_names_ids_and_origin(run: tuple[dict[str, Any], dict[str, list[str]]]) -> None:
    configs, _ = run
    air = configs["air"]
    assert air["dev"]["ids"] == ["rtupoll_north_air"]
    assert air["cmps"]["pm25"]["unique_id"] == "rtupoll_north_air_pm25"
    assert air["cmps"]["pm25"]["name"] == "PM2.5 concentration"
    assert configs["gas"]["cmps"]["warning_WARMUP_WARNING"]["name"] == \
        "Sensor warning state: Warm-up"
    assert all("rtupoll_rtupoll" not in json.dumps(c) for c in configs.values())
    assert air["o"]["name"] == "rtupoll" and "url" not in air["o"] and air["o"]["sw"]
    number = configs["room"]["cmps"]["temperature_correction_set"]
    assert (number["min"], number["max"], number["step"], number["mode"]) == \
        (-10, 10, 0.1, "box")
    assert configs["room"]["cmps"]["temperature"]["suggested_display_precision"] == 1
    # the energy totals named for what they measure, told apart (HA's Energy dashboard)
    grid = configs["grid"]["cmps"]
    assert [grid[n]["name"] for n in ("import_active_energy", "export_active_energy")] == \
        ["Import energy total", "Export energy total"]
    assert grid["total_power_factor"]["device_class"] == "power_factor"
    # a correction is no temperature: its unit, no class HA would convert by
    corr = configs["room"]["cmps"]["temperature_correction"]
    assert corr["unit_of_measurement"] == "°C" and "device_class" not in corr
    # Last seen changes with every message: disabled until a user enables it
    assert all(c["cmps"]["_last_seen"]["enabled_by_default"] is False
               for c in configs.values())


def profile_values(field: Any) -> list[float]:
    """Values the profile allows a writable number: its values:, its range's ends, else
    its type's extremes at its scale."""
    if field.values:
        return list(field.values)
    lo, hi = value_range(field.layout)
    return [field.minimum if field.minimum is not None else lo,
            field.maximum if field.maximum is not None else hi]


def test_number_boxes_admit_every_value_the_profiles_allow() -> None:
    import os

    here = Path(__file__).parents[2] / "profiles"
    checked = 0
    for file in sorted(os.listdir(here)):
        if not file.endswith(".yaml"):
            continue
        profile = load_one(file[:-5], [])
        for f in profile.fields:
            if not f.writable or f.enum or f.flags or \
                    f.layout.type in (DataType.STRING, DataType.BOOL):
                continue
            (control,) = [c for cid, c in ha.components(f, controls=True).items()
                          if cid.endswith("_set")]
            for v in profile_values(f):
                assert control["min"] <= v <= control["max"], (profile.id, f.name, v)
                # a value HA offers is a whole number of steps from the box's minimum
                steps = (v - control["min"]) / control["step"]
                assert abs(steps - round(steps)) < 1e-6 or f.layout.type.is_float, \
                    (profile.id, f.name, v, control)
            assert control["step"] >= ha.MIN_STEP
            checked += 1
    assert checked >= 10
