"""Readings -> MQTT messages (``outputs.mqtt_state``), the gateway identity
(``outputs.fleet``), and what a command may carry: all without a broker.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from rtupoll.config import mqtt_settings
from rtupoll.config.library import load_one
from rtupoll.config.mqtt_settings import DeviceOptions, parse_url
from rtupoll.config.site import DeviceConfig, from_specs, load_site
from rtupoll.errors import ConfigError, ProfileError, RefusedError, UsageError
from rtupoll.jobs.stats import Reading, Status
from rtupoll.model.interpret import interpret
from rtupoll.outputs import fleet
from rtupoll.outputs.mqtt import from_options
from rtupoll.outputs.mqtt_commands import MAX_DEPTH, MAX_PAYLOAD, depth, plan_get, plan_set
from rtupoll.outputs.mqtt_state import StatePublisher


class Clock:
    now = 100.0

    def __call__(self) -> float:
        return self.now


def meter() -> DeviceConfig:
    return from_specs("/dev/null", [("eastron-sdm120", 7)], check_serial=False
                      ).buses[0].devices[0]


def ok(dev: DeviceConfig, name: str, words: tuple[int, ...]) -> Reading:
    f = dev.profile.field(name)
    return Reading(1.7e9, dev, f, interpret(f, words))


def bad(dev: DeviceConfig, name: str, status: Status, error: str) -> Reading:
    return Reading(1.7e9, dev, dev.profile.field(name), None, status, error)


F32_230 = (0x4366, 0x0000)  # 230.0 as an ABCD f32
F32_12 = (0x4140, 0x0000)  # 12.0


def publisher(publish: str = "every_scan", **kw: Any) -> tuple[StatePublisher, Clock]:
    s = parse_url("mqtt://b/plant")
    s = s.__class__(**{**s.__dict__, "defaults": DeviceOptions(publish=publish, **kw)})
    clock = Clock()
    return StatePublisher(s, {"eastron-sdm120@7": "m"}, clock), clock


def states(out: list[Any]) -> list[dict[str, Any]]:
    return [json.loads(o.payload) for o in out if o.topic == "plant/m"]


def test_every_polled_field_is_in_every_state_with_its_last_value() -> None:
    dev = meter()
    pub, _ = publisher()
    first = states(pub.readings(dev, True, 1.7e9, [
        ok(dev, "voltage", F32_230), ok(dev, "import_active_energy", F32_12)]))[0]
    assert first["voltage"] == 230.0 and first["import_active_energy"] == 12.0
    assert set(first) == {f.name for f in dev.fields} | {"last_seen", "_rtupoll"}
    assert first["frequency"] is None  # never read yet: null, but there
    # the next scan reads only the fast block: the energy keeps its value
    second = states(pub.readings(dev, True, 1.7e9, [ok(dev, "voltage", (0x4367, 0))]))[0]
    assert second["voltage"] == 231.0 and second["import_active_energy"] == 12.0
    assert second["_rtupoll"] == {"status": "ok", "error": None}
    # a failed read is null, never the stale value; the status says why
    third = states(pub.readings(dev, True, 1.7e9, [
        ok(dev, "voltage", F32_230),
        bad(dev, "import_active_energy", Status.EXCEPTION, "device 7 answered 02")]))[0]
    assert third["import_active_energy"] is None
    assert third["_rtupoll"] == {"status": "partial",
                                 "error": "exception: device 7 answered 02"}
    fourth = states(pub.readings(dev, False, 1.7e9, [
        bad(dev, "voltage", Status.TIMEOUT, "no reply"),
        bad(dev, "frequency", Status.SKIPPED, "skipped after a timeout")]))[0]
    assert fourth["_rtupoll"] == {"status": "failed", "error": "timeout: no reply"}


def test_the_status_is_never_ok_while_a_field_is_null_for_a_failed_read() -> None:
    """A slow field whose last read failed (the port went away) stays null in the scans
    that do not read it: those say partial, with its failure, until it has a value."""
    dev = meter()
    pub, _ = publisher()
    pub.readings(dev, True, 1.7e9, [ok(dev, "voltage", F32_230),
                                    ok(dev, "import_active_energy", F32_12)])
    lost = states(pub.readings(dev, True, 1.7e9, [
        bad(dev, "voltage", Status.PORT, "/dev/ttyUSB0: gone"),
        bad(dev, "import_active_energy", Status.PORT, "/dev/ttyUSB0: gone")]))[0]
    assert lost["_rtupoll"] == {"status": "failed", "error": "port: /dev/ttyUSB0: gone"}
    back = states(pub.readings(dev, True, 1.7e9, [ok(dev, "voltage", F32_230)]))[0]
    assert back["voltage"] == 230.0 and back["import_active_energy"] is None
    assert back["_rtupoll"] == {"status": "partial", "error": "port: /dev/ttyUSB0: gone"}
    read = states(pub.readings(dev, True, 1.7e9, [ok(dev, "voltage", F32_230),
                                                  ok(dev, "import_active_energy", F32_12)]))
    assert read[0]["import_active_energy"] == 12.0
    assert read[0]["_rtupoll"] == {"status": "ok", "error": None}
    # read, but no value from the device (a NaN float, a sentinel): null, so partial
    nan = states(pub.readings(dev, True, 1.7e9, [ok(dev, "voltage", (0x7FC0, 0)),
                                                 ok(dev, "import_active_energy", F32_12)]))[0]
    assert nan["voltage"] is None
    assert nan["_rtupoll"] == {"status": "partial", "error": "no value: voltage is nan"}
    # a field this generation lacks is null and no failure
    absent = states(pub.readings(dev, True, 1.7e9, [
        ok(dev, "voltage", F32_230),
        bad(dev, "frequency", Status.ABSENT, "not in map version 0")]))[0]
    assert absent["frequency"] is None and absent["_rtupoll"]["status"] == "ok"


def test_availability_when_it_changes_and_again_after_a_reconnect() -> None:
    dev = meter()
    pub, _ = publisher()
    out = pub.readings(dev, True, None, [ok(dev, "voltage", F32_230)])
    assert [(o.topic, o.payload, o.retain) for o in out if o.topic.endswith("availability")] \
        == [("plant/m/availability", "online", True)]
    again = pub.readings(dev, True, None, [ok(dev, "voltage", F32_230)])
    assert not [o for o in again if o.topic.endswith("availability")]
    assert {o.topic for o in pub.latest()} == {"plant/m", "plant/m/availability"}
    assert [o.payload for o in pub.offline()] == ["offline"]


def test_on_change_waits_for_a_change_or_the_maximum_silence() -> None:
    dev = meter()
    pub, clock = publisher("on_change", max_silence=10)
    assert states(pub.readings(dev, True, 1.0, [ok(dev, "voltage", F32_230)]))
    clock.now += 1
    assert not states(pub.readings(dev, True, 1.0, [ok(dev, "voltage", F32_230)]))
    clock.now += 1
    assert states(pub.readings(dev, True, 1.0, [ok(dev, "voltage", (0x4367, 0))]))
    clock.now += 10
    assert states(pub.readings(dev, True, 1.0, [ok(dev, "voltage", (0x4367, 0))]))
    pub.forced.add("m")  # a get
    assert states(pub.readings(dev, True, 1.0, [ok(dev, "voltage", (0x4367, 0))]))


def test_a_sentinel_is_null_and_named_under_rtupoll_while_the_field_holds_it() -> None:
    """An R4DCB08 channel with no sensor (0x8000, its profile's NO_SENSOR): the value is
    null, as before, and ``_rtupoll.sentinels`` names it, in this scan and in those that
    do not read it, until a read gives it a value; a message with none has no such key."""
    dev = from_specs("/dev/null", [("r4dcb08", 1)], check_serial=False).buses[0].devices[0]
    s = parse_url("mqtt://b/plant")
    pub = StatePublisher(s.__class__(**{**s.__dict__, "defaults": DeviceOptions(
        publish="on_change", max_silence=300)}), {dev.name: "t"}, Clock())

    def state(*readings: Reading) -> dict[str, Any] | None:
        got = [json.loads(o.payload) for o in pub.readings(dev, True, 1.7e9, readings)
               if o.topic == "plant/t"]
        return got[0] if got else None

    one = state(ok(dev, "temperature_1", (0x8000,)), ok(dev, "temperature_3", (0x8000,)),
                ok(dev, "temperature_2", (215,)))
    assert one is not None
    assert one["temperature_1"] is None and one["temperature_2"] == 21.5
    assert one["_rtupoll"] == {
        "status": "partial", "error": "no value: temperature_1 is NO_SENSOR",
        "sentinels": {"temperature_1": "NO_SENSOR", "temperature_3": "NO_SENSOR"}}
    assert state(ok(dev, "temperature_2", (215,))) is None  # on_change: nothing new
    # a read that fails is no sentinel; a value ends it
    two = state(bad(dev, "temperature_1", Status.TIMEOUT, "no reply"),
                ok(dev, "temperature_2", (215,)))
    assert two is not None and two["_rtupoll"]["sentinels"] == {"temperature_3": "NO_SENSOR"}
    three = state(ok(dev, "temperature_1", (200,)), ok(dev, "temperature_3", (219,)))
    assert three is not None and three["_rtupoll"] == {"status": "ok", "error": None}
    assert (three["temperature_1"], three["temperature_3"]) == (20.0, 21.9)
    # then the sentinels are all that change (the values null, the error the first
    # one's): on_change publishes each
    four = state(bad(dev, "temperature_1", Status.TIMEOUT, "no reply"),
                 ok(dev, "temperature_3", (0x8000,)))
    assert four is not None and four["_rtupoll"] == {
        "status": "partial", "error": "timeout: no reply",
        "sentinels": {"temperature_3": "NO_SENSOR"}}
    five = state(bad(dev, "temperature_1", Status.TIMEOUT, "no reply"),
                 bad(dev, "temperature_3", Status.EXCEPTION, "device 1 answered 02"),
                 ok(dev, "temperature_2", (215,)))
    assert five is not None and five["_rtupoll"] == {"status": "partial",
                                                     "error": "timeout: no reply"}


# -- identity -----------------------------------------------------------------

def test_the_gateway_id_defaults_to_the_host_name() -> None:
    assert mqtt_settings.default_gateway_id("Pump-House.example.com") == "pump-house_example_com"
    assert mqtt_settings.default_gateway_id("###") == "rtupoll"
    s = parse_url("mqtt://broker")
    assert s.gateway_id == mqtt_settings.default_gateway_id()
    assert s.base == f"rtupoll/{s.gateway_id}"
    assert parse_url("mqtt://broker/site/north").base == "site/north"  # given: as given


def test_mqtt_id_and_the_site_file(tmp_path: Path) -> None:
    site = from_specs("/dev/null", [("huiwen-aq", 3)])
    s = from_options(site, "mqtt://broker", allow_writes=False, gateway_id="north-1")
    assert s is not None and (s.gateway_id, s.base) == ("north-1", "rtupoll/north-1")
    with pytest.raises(UsageError, match="a gateway id is 1 to 64 of a-z"):
        from_options(site, "mqtt://broker", allow_writes=False, gateway_id="North 1")
    with pytest.raises(UsageError, match="--mqtt-id needs --mqtt URL"):
        from_options(site, None, allow_writes=False, gateway_id="x")
    path = tmp_path / "site.yaml"
    text = ("buses:\n  - port: tcp://127.0.0.1:5020\n    devices:\n"
            "      - {name: air, profile: huiwen-aq, address: 3}\n"
            "mqtt:\n  url: mqtt://broker\n  gateway_id: GW\n")
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"site.yaml:7: mqtt.gateway_id: 'GW': a gateway id"):
        load_site(path)
    path.write_text(text.replace("GW", "gw"))
    loaded = load_site(path).mqtt
    assert loaded is not None and loaded.base == "rtupoll/gw"


def test_bridge_info_describes_devices_and_fields() -> None:
    site = from_specs("/dev/null", [("huiwen-aq", 3), ("net-irnet-pro", 1)], baudrate=9600)
    info = fleet.bridge_info("gw", "rtupoll/gw", site.devices(),
                             {"huiwen-aq@3": "huiwen-aq_3", "net-irnet-pro@1": "net-irnet-pro_1"},
                             "1.2.3")
    assert (info["gateway"], info["base"], info["version"]) == ("gw", "rtupoll/gw", "1.2.3")
    air = info["devices"]["huiwen-aq_3"]
    assert (air["name"], air["profile"], air["address"], air["bus"]) == \
        ("huiwen-aq@3", "huiwen-aq", 3, "/dev/null")
    assert air["fields"]["tvoc"] == {"label": "TVOC concentration", "unit": "ppm",
                                     "kind": "number", "precision": 3}
    gas = info["devices"]["net-irnet-pro_1"]["fields"]
    assert (gas["error"]["kind"], gas["warning"]["kind"]) == ("enum", "flags")
    assert gas["error"]["precision"] is None
    assert "sentinels" not in air["fields"]["tvoc"]
    site = from_specs("/dev/null", [("r4dcb08", 1)], baudrate=9600)
    info = fleet.bridge_info("gw", "rtupoll/gw", site.devices(), {}, "1.2.3")
    assert info["devices"]["r4dcb08@1"]["fields"]["temperature_1"] == {
        "label": "Temperature 1", "unit": "°C", "kind": "number", "precision": 1,
        "sentinels": {"NO_SENSOR": "error"}}


def test_names_no_field_can_take(tmp_path: Path) -> None:
    base = Path(__file__).parents[2] / "profiles" / "xy-md02.yaml"
    for reserved in ("_rtupoll", "last_seen"):
        text = base.read_text().replace("name: humidity,", f"name: {reserved},", 1)
        assert text != base.read_text()
        (tmp_path / "xy-md02.yaml").write_text(text)
        with pytest.raises(ProfileError, match=f"'{reserved}' is reserved"):
            load_one(str(tmp_path / "xy-md02.yaml"), [])


def test_an_empty_device_name_is_refused_with_its_line(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    path.write_text("buses:\n  - port: tcp://127.0.0.1:5020\n    devices:\n"
                    "      - {name: air, profile: huiwen-aq, address: 3}\n"
                    "      - {name: '', profile: radar-level, address: 4}\n")
    with pytest.raises(ConfigError) as err:
        load_site(path)
    assert str(err.value).startswith(f"{path}:5: buses[0].devices[1].name: the device name "
                                      "is empty")


# -- what a command may carry ---------------------------------------------------

def irnet() -> DeviceConfig:
    return from_specs("/dev/null", [("net-irnet-pro", 1)], check_serial=False
                      ).buses[0].devices[0]


@pytest.mark.parametrize("payload, error, why", [
    (b'{"calibration_gas_level": 1e39}', RefusedError, "outside what the field can hold"),
    (b'{"calibration_gas_level": -1e39}', RefusedError, "outside what the field can hold"),
    (b'{"calibration_gas_level": 1e400}', RefusedError, "outside what the field can hold"),
    (b'{"calibration_gas_level": "1_0"}', UsageError, "is not a number"),
    ('{"calibration_gas_level": "\uff11"}'.encode(), UsageError, "is not a number"),
    (b'{"calibration_gas_level": "0x10"}', UsageError, "is not a number"),
    (b'{"calibration_gas_level": " 5"}', UsageError, "is not a number"),
    (b'{"calibration_gas_level": "1e1"}', UsageError, "is not a number"),
    (b'{"calibration_gas_level": "1E3"}', UsageError, "is not a number"),
    (b'{"calibration_gas_level": 1, "calibration_gas_level": 2}', UsageError,
     'the key "calibration_gas_level" twice'),
    (b'{"fields": {"a": 1, "a": 1}}', UsageError, 'the key "a" twice'),
    (b'{"calibration_gas_level": true}', UsageError, "is not a value for it"),
    (b'{"calibration_gas_level": [1]}', UsageError, "is not a value for it"),
    (b'{"calibration_gas_level": 1' + b"0" * 5000 + b"}", UsageError, "not JSON"),
    (b"[" * 100_000, UsageError, f"at most {MAX_PAYLOAD}"),
    (b"[" * 1000 + b"]" * 1000, UsageError, f"deeper than {MAX_DEPTH}"),
    (b'{"a": {"b": {"c": {"d": {"e": 1}}}}}', UsageError, f"deeper than {MAX_DEPTH}"),
    (b"\xff\xfe", UsageError, "not JSON"),
])
def test_a_set_takes_json_numbers_and_plain_decimals_only(payload: bytes,
                                                          error: type[Exception],
                                                          why: str) -> None:
    with pytest.raises(error, match=why):
        plan_set(irnet(), payload, writes_on=True)


@pytest.mark.parametrize("value, expect", [("12.5", 12.5), ("150", 150), (150, 150),
                                           (-0.5, -0.5), ("+2", 2), (1e3, 1000),
                                           ("2.", 2), (".5", 0.5)])
def test_numbers_that_are_numbers(value: Any, expect: float) -> None:
    (op,) = plan_set(irnet(), json.dumps({"calibration_gas_level": value}).encode(),
                     writes_on=True)
    assert op.value == expect


def test_get_payloads_are_bounded_too() -> None:
    with pytest.raises(UsageError, match="deeper than"):
        plan_get(irnet(), b"[" * 10 + b"]" * 10)
    with pytest.raises(UsageError, match="at most"):
        plan_get(irnet(), b"[" * (MAX_PAYLOAD + 1))
    with pytest.raises(UsageError, match='the key "fields" twice'):
        plan_get(irnet(), b'{"fields": ["co2"], "fields": []}')


def test_depth_ignores_brackets_in_strings() -> None:
    assert depth(b'{"a": "[[[[{{{{\\"[["}') == 1
    assert depth(b"[[1], [[2]]]") == 3
