"""MQTT without a process of its own: discovery payloads, plain values, the scheduler's
hooks for commands (in virtual time) and the service's live-table line.

The end-to-end behaviour (a real mosquitto, the real CLI) is in ``test_mqtt_cli.py``.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import pytest
from site_files import site_file
from virtual import START, ScriptedBus, VirtualClock

from rtupoll.config.site import from_specs, load_site
from rtupoll.errors import UsageError
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.outputs import homeassistant as ha
from rtupoll.outputs.mqtt import plain, topic_name
from rtupoll.rtu import Table

# -- Home Assistant discovery -------------------------------------------------

def discovery(spec: tuple[str, int], *, controls: dict[str, bool] | None = None) -> dict:
    site = from_specs("/dev/null", [spec], check_serial=False)
    bus, dev = next(site.devices())
    return ha.device_config(dev, bus, gateway_id="gw1", base="plant",
                            topic=topic_name(dev.name), controls=controls or {}, qos=0)


def test_units_give_device_and_state_classes() -> None:
    cmps = discovery(("huiwen-aq", 3))["cmps"]
    expect = {"co2": ("ppm", "carbon_dioxide"), "pm25": ("µg/m³", "pm25"),
              "temperature": ("°C", "temperature"), "humidity": ("%", "humidity"),
              "tvoc": ("ppm", "volatile_organic_compounds_parts")}
    for name, (unit, cls) in expect.items():
        c = cmps[name]
        assert (c["p"], c["unit_of_measurement"], c["device_class"], c["state_class"]) == \
            ("sensor", unit, cls, "measurement"), name
        assert c["value_template"] == f"{{{{ value_json['{name}'] }}}}"
        assert c["unique_id"] == f"rtupoll_gw1_huiwen-aq_3_{name}"
    level = cmps["co2_level"]
    assert level["device_class"] == "enum" and "unit_of_measurement" not in level
    assert level["options"][-1] == "unknown" and "GOOD" in level["options"]


def test_flags_are_binary_sensors_and_errors_are_problems() -> None:
    cmps = discovery(("net-irnet-pro", 1))["cmps"]
    warm = cmps["warning_WARMUP_WARNING"]
    assert warm["p"] == "binary_sensor" and "device_class" not in warm  # severity info
    assert cmps["warning_INVALID_ACTIVE_WARNING"]["device_class"] == "problem"
    assert cmps["temperature"]["unit_of_measurement"] == "K"
    assert cmps["temperature"]["device_class"] == "temperature"


def test_device_availability_and_via_bus() -> None:
    cfg = discovery(("radar-level", 4))
    assert cfg["dev"]["ids"] == ["rtupoll_gw1_radar-level_4"]
    assert cfg["dev"]["via_device"] == ha.bus_object_id("gw1", "/dev/null")
    assert cfg["availability"] == [{"topic": "plant/bridge/state"},
                                   {"topic": "plant/radar-level_4/availability"}]
    assert cfg["availability_mode"] == "all" and cfg["state_topic"] == "plant/radar-level_4"
    assert ha.is_ours(cfg, "gw1", "plant") and not ha.is_ours(cfg, "gw1", "plant2")
    assert not ha.is_ours(cfg, "gw1", "pla") and not ha.is_ours(cfg, "gw2", "plant")
    assert not ha.is_ours(cfg, "gw", "plant")


def test_writable_fields_become_controls_only_when_allowed() -> None:
    site = from_specs("/dev/null", [("banner-ez-array", 5)], fields=["measurement_1_mode"])
    bus, dev = next(site.devices())
    off = ha.device_config(dev, bus, gateway_id="g", base="b", topic="c", controls={},
                           qos=0)["cmps"]
    assert "measurement_1_mode_set" not in off
    on = ha.device_config(dev, bus, gateway_id="g", base="b", topic="c",
                          controls={"measurement_1_mode": True}, qos=0)["cmps"]
    select = on["measurement_1_mode_set"]
    assert (select["p"], select["command_topic"]) == ("select", "b/c/set")
    assert "TBB" in select["options"]
    assert json.loads(select["command_template"].replace("{{ value }}", "TBB")) == \
        {"measurement_1_mode": "TBB"}


def test_plain_values() -> None:
    assert [plain(v) for v in (12.5, "GOOD", ["A", "B"], True)] == \
        ["12.5", "GOOD", '["A","B"]', "true"]


# -- the scheduler's hooks, in virtual time ------------------------------------

def test_poll_now_and_submit_run_ahead_of_the_schedule() -> None:
    """A device read a minute ago is read again at once (the virtual clock does not move
    between), and a submitted job runs on the bus between two cycles."""
    clock = VirtualClock(START)
    site = from_specs("/dev/null", [("radar-level", 4), ("huiwen-aq", 3)], interval=60,
                      check_serial=False)
    fake = ScriptedBus(clock)  # answers every read at once (20 ms of virtual time)
    bp = BusPoller(site.buses[0], fake, backoff=Backoff(), clock=clock, wall=clock)
    cycles: list[str] = []

    async def main() -> None:
        stop = asyncio.Event()
        task = asyncio.create_task(bp.run(lambda d, r: cycles.append(d.config.name), stop))
        async def until(n: int) -> None:
            while len(cycles) < n:
                assert not task.done(), task.exception()  # the bus loop must keep running
                await asyncio.sleep(0)

        await until(2)
        at = clock.now
        bp.poll_now(bp.devices[1])
        await until(3)
        assert cycles[2] == "huiwen-aq@3" and clock.now - at < 1  # no waiting for the minute
        calls = len(fake.calls)
        got = await bp.submit(lambda transport: transport.read(
            4, Table.INPUT, 1, 1, timeout=0.1))
        assert got.values == (0,) and len(fake.calls) == calls + 1
        stop.set()
        await task

    asyncio.run(asyncio.wait_for(main(), 10))


def test_a_missing_aiomqtt_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from rtupoll.errors import install_command
    from rtupoll.outputs.mqtt import from_options

    monkeypatch.setitem(sys.modules, "aiomqtt", None)  # import aiomqtt -> ImportError
    site = from_specs("/dev/null", [("radar-level", 4)])
    with pytest.raises(UsageError) as err:
        from_options(site, "mqtt://broker", allow_writes=False)
    assert str(err.value) == ("MQTT (--mqtt, or mqtt: in the site file) needs aiomqtt: "
                              + install_command("mqtt")[1])
    assert err.value.exit_code == 2


def test_the_live_table_footer_says_where_and_how(tmp_path: Path) -> None:
    from rtupoll.outputs.mqtt import MqttService

    site = load_site(site_file(tmp_path, "mqtt:\n  url: mqtt://broker.lan/plant\n"))
    assert site.mqtt is not None

    async def footer() -> str:
        assert site.mqtt is not None
        service = MqttService(site.mqtt, site, log_lines=False)
        service.outbox.put("plant/air", "{}", retain=False, qos=0)
        text = service.footer().plain
        c = service.connection
        c.lost_at, c.last_error = time.monotonic() - 12, "connection refused"
        return text + "\n" + service.footer().plain

    connecting, lost = asyncio.run(footer()).split("\n")
    assert connecting == ("mqtt mqtt://broker.lan:1883/plant · connecting · 0 published · "
                          "1 waiting")
    assert lost.startswith("mqtt mqtt://broker.lan:1883/plant · broker lost 12 s ago "
                           "(connection refused), reconnecting")
