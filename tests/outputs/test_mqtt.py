"""MQTT without a process of its own: settings, discovery payloads, command checks, the
scheduler's hooks for commands (in virtual time) and the service's live-table line.

The end-to-end behaviour (a real mosquitto, the real CLI) is in ``test_mqtt_cli.py``.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import pytest
from virtual import START, ScriptedBus, VirtualClock

from rtupoll.config.mqtt_settings import parse_url
from rtupoll.config.site import BusConfig, from_specs, load_site
from rtupoll.errors import ConfigError, RefusedError, UsageError
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.outputs import homeassistant as ha
from rtupoll.outputs.mqtt import plain, topic_name
from rtupoll.outputs.mqtt_commands import WRITES_OFF, failed, plan_get, plan_set, protected
from rtupoll.rtu import Table


def site_file(tmp_path: Path, mqtt: str) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(
        "buses:\n"
        "  - name: plant\n"
        "    port: tcp://127.0.0.1:5020\n"
        "    baudrate: 9600\n"
        "    devices:\n"
        "      - {name: air, profile: huiwen-aq, address: 3}\n"
        "      - {name: tank, profile: radar-level, address: 4}\n" + mqtt)
    return path


# -- settings ----------------------------------------------------------------

def test_url_gives_broker_credentials_and_base() -> None:
    s = parse_url("mqtts://gw:p%40ss@broker.lan/site/north")
    assert (s.host, s.port, s.tls, s.username, s.password, s.base) == \
        ("broker.lan", 8883, True, "gw", "p@ss", "site/north")
    plain_url = parse_url("mqtt://10.0.0.2:1884")
    assert (plain_url.port, plain_url.tls, plain_url.base_topic, plain_url.username) == \
        (1884, False, None, None)
    assert plain_url.base == f"rtupoll/{plain_url.gateway_id}"  # the default


def test_url_user_without_password_takes_it_from_the_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RTUPOLL_MQTT_PASSWORD", "from-env")
    assert parse_url("mqtt://gw@h").password == "from-env"


@pytest.mark.parametrize("url, why", [
    ("http://h", "expected mqtt://"),
    ("mqtt://", "no broker host"),
    ("mqtt://h/a/+/b", "not a usable MQTT topic"),
    ("mqtt://h:99999", "Port out of range"),
])
def test_bad_urls_are_one_line(url: str, why: str) -> None:
    with pytest.raises(UsageError, match=why.replace("+", r"\+")):
        parse_url(url)


def test_site_section(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PLANT_MQTT", "s3cret")
    site = load_site(site_file(tmp_path, (
        "mqtt:\n"
        "  url: mqtt://broker.lan/plant\n"
        "  username: gw\n"
        "  password_env: PLANT_MQTT\n"
        "  qos: 1\n"
        "  publish: on_change\n"
        "  max_silence: 60\n"
        "  devices:\n"
        "    tank: {publish: every_scan, allow: [baud_rate], field_topics: true}\n")))
    s = site.mqtt
    assert s is not None
    assert (s.host, s.username, s.password, s.qos, s.base) == ("broker.lan", "gw", "s3cret", 1,
                                                               "plant")
    assert (s.options("air").publish, s.options("air").max_silence) == ("on_change", 60)
    tank = s.options("tank")
    assert (tank.publish, tank.allow, tank.field_topics, tank.max_silence) == \
        ("every_scan", ("baud_rate",), True, 60)
    # a password file, relative to the site file
    (tmp_path / "mqtt-password").write_text("from-file\n")
    other = load_site(site_file(tmp_path, "mqtt:\n  url: mqtt://gw@broker.lan\n"
                                          "  password_file: mqtt-password\n")).mqtt
    assert other is not None and (other.username, other.password) == ("gw", "from-file")
    # --mqtt URL replaces the broker, keeps the section's other choices
    moved = s.with_url("mqtt://other:1999")
    assert (moved.host, moved.port, moved.base, moved.username, moved.qos) == \
        ("other", 1999, "plant", "gw", 1)


@pytest.mark.parametrize("section, where", [
    ("mqtt:\n  url: mqtt://b\n  qso: 1\n", "10: mqtt.qso: unknown key (did you mean 'qos'?)"),
    ("mqtt:\n  url: mqtt://b\n  username: u\n  password_env: NOPE_NOT_SET\n",
     "11: mqtt.password_env: the environment variable NOPE_NOT_SET is not set"),
    ("mqtt:\n  url: mqtt://b\n  username: u\n  password_file: missing.txt\n",
     "11: mqtt.password_file: cannot read"),
    ("mqtt:\n  url: mqtt://b\n  devices:\n    pump: {publish: on_change}\n",
     "11: mqtt.devices.pump: no device 'pump' in this site file"),
    ("mqtt:\n  url: mqtt://b\n  devices:\n    tank: {allow: [level_cm]}\n",
     "11: mqtt.devices.tank.allow[0]: level_cm is read-only"),
    ("mqtt:\n  url: mqtt://b\n  publish: sometimes\n",
     "10: mqtt.publish: 'sometimes' is not one of: every_scan, on_change"),
    ("mqtt:\n  url: ftp://b\n", "9: mqtt.url: expected mqtt://"),
])
def test_site_section_mistakes_are_file_line(tmp_path: Path, section: str, where: str) -> None:
    path = site_file(tmp_path, section)
    with pytest.raises(ConfigError) as err:
        load_site(path)
    assert str(err.value).startswith(f"{path}:{where}")


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


# -- commands ----------------------------------------------------------------

def banner() -> BusConfig:
    return from_specs("/dev/null", [("banner-ez-array", 5)]).buses[0]


def test_set_is_refused_while_writes_are_off() -> None:
    with pytest.raises(RefusedError, match="writes over MQTT are off"):
        plan_set(banner().devices[0], b'{"measurement_1_mode": "TBB"}', writes_on=False)
    assert failed(RefusedError(WRITES_OFF)) == {"status": "refused", "exit_code": 8,
                                                "error": WRITES_OFF}


def test_a_results_status_is_its_error_classs_word_as_the_docs_list_them() -> None:
    """``status`` in a command's result comes from the error class (``errors.py``, beside
    its exit code): every word the docs list, with its exit code, and "error" for the
    rest."""
    import re

    from rtupoll import errors

    docs = (Path(__file__).parents[2] / "docs" / "mqtt.md").read_text(encoding="utf-8")
    listed = docs.split("(`status`: ", 1)[1].split(")", 1)[0]
    said = {word: int(code) for word, code in re.findall(r"`(\w+)` (\d+)", listed)}
    classes = [c for c in vars(errors).values()
               if isinstance(c, type) and issubclass(c, errors.RtupollError)]
    owned = {c.status: c.exit_code for c in classes if "status" in c.__dict__}
    assert owned == {**said, "error": 1}
    assert failed(errors.EncodeError("x"))["status"] == "refused"  # a subclass: its base's
    assert failed(errors.ConfigError("x"))["status"] == "error"
    assert failed(errors.DeviceException(2, unit=1))["status"] == "exception"


@pytest.mark.parametrize("payload, error, why", [
    (b'{"measurement_1": 3}', RefusedError, "measurement_1 is read-only"),
    (b'{"measurement_1_mode": "NOPE"}', RefusedError, "'NOPE' is not one of"),
    (b'{"slave_address": 9}', RefusedError, "the device's own address"),
    (b'{"nonesuch": 1}', UsageError, "has no field 'nonesuch'"),
    (b"[1, 2]", UsageError, "expected a JSON object"),
    (b"{not json", UsageError, "not JSON"),
])
def test_set_checks_everything_before_sending(payload: bytes, error: type[Exception],
                                              why: str) -> None:
    with pytest.raises(error, match=why):
        plan_set(banner().devices[0], payload, writes_on=True)


def test_address_and_baud_fields_need_a_per_field_allowance() -> None:
    radar = from_specs("/dev/null", [("radar-level", 4)]).buses[0].devices[0]
    p = radar.profile
    assert protected(p, p.field("baud_rate")) == "the device's baud rate"
    assert protected(p, p.field("slave_address")) == "the device's own address"
    with pytest.raises(RefusedError, match=r"allow: \[baud_rate\]"):
        plan_set(radar, b'{"baud_rate": 19200}', writes_on=True)
    (op,) = plan_set(radar, b'{"baud_rate": 19200}', writes_on=True, allow=["baud_rate"])
    assert (op.field.name, op.words) == ("baud_rate", (192,))


def test_get_takes_nothing_a_list_or_fields() -> None:
    dev = banner().devices[0]
    assert plan_get(dev, b"") is None and plan_get(dev, b"{}") is None
    assert [f.name for f in plan_get(dev, b'["emitter_channels"]') or []] == ["emitter_channels"]
    assert [f.name for f in plan_get(dev, b'{"fields": ["measurement_1"]}') or []] == \
        ["measurement_1"]
    with pytest.raises(RefusedError, match="never polled"):
        plan_get(dev, b'["analog_1_peak"]')


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
