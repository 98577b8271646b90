"""Site configuration: what a good file gives, and the exact error for each broken one."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.site import from_specs, load_site
from rtupoll.errors import ConfigError, RtupollError, UsageError

SITE = Path(__file__).parents[1] / "fixtures" / "site"


def test_a_good_site_gives_buses_devices_and_their_settings() -> None:
    site = load_site(SITE / "good.yaml")
    plant, gateway = site.buses
    assert (plant.name, plant.port, plant.serial_text) == ("plant", "/dev/ttyUSB0", "9600 8N1")
    assert [d.name for d in plant.devices] == ["air", "radar-level@5", "curtain"]
    air, radar, curtain = plant.devices
    assert [f.name for f in air.fields] == ["co2", "temperature", "co2_level"]
    assert air.interval == 2 and air.response_timeout == 0.5  # the profile's timeout
    assert (radar.response_timeout, radar.retry_count) == (0.2, 0)  # overrides
    assert curtain.address == 0x41
    # no field list: the profile's default poll set, never a poll: never field
    assert curtain.fields == curtain.profile.default_fields()
    assert "analog_1_peak" not in [f.name for f in curtain.fields]
    # the gateway's serial settings come from its only device's profile, DTR included
    assert gateway.port == "tcp://10.0.0.5:502"
    assert gateway.serial_text == "115200 8N1" and gateway.deassert_dtr
    assert not plant.deassert_dtr


BROKEN = {
    "unknown-key": "3: buses[0].baudrat: unknown key (did you mean 'baudrate'?)",
    "missing-port": "2: buses[0]: missing required key 'port'",
    "duplicate-address": "10: buses[0].devices[1].address: address 3 is already used by air "
                         "(line 5)",
    "baud-contradiction": "7: buses[0].devices[1].profile: huiwen-aq cannot run at 19200 baud, "
                          "the speed of bus plant (set at line 4); it supports 4800, 9600, "
                          "115200",
    "parity-contradiction": "6: buses[0].devices[0].profile: radar-level uses parity N, bus "
                            "/dev/ttyUSB0 uses E (set at line 4)",
    "any-address-shared": "7: buses[0].devices[1].address: 254 (0xFE) is the 'any device' "
                          "address of co2meter-an117: every such device answers it, so it only "
                          "works alone on a bus, and lab has 2 devices",
    "reserved-address": "4: buses[0].devices[0].address: 204 (0xCC) is reserved: CO2Meter's "
                        "proprietary protocol uses it",
    "reserved-by-neighbour": "6: buses[0].devices[1].address: 204 (0xCC) is reserved on a bus "
                             "with co2: CO2Meter's proprietary protocol uses it",
    "any-of-neighbour": "6: buses[0].devices[1].address: co2 also answers 254 (0xFE), its "
                        "'any device' address, so the replies would collide",
    "unknown-profile": "4: buses[0].devices[0].profile: no profile 'huiwen' (did you mean "
                       "'huiwen-aq'?); see 'rtupoll profiles list'",
    "unknown-field": "6: buses[0].devices[0].fields[0]: net-irnet-pro has no field "
                     "'concentraton' (did you mean 'concentration'?)",
    "never-field": "8: buses[0].devices[0].fields[1]: analog_1_peak is never polled: reading it "
                   "has side effects (Analog output 1 peak; READING IT RESETS THE PEAK); use "
                   "'rtupoll read'",
    "duplicate-field": "6: buses[0].devices[0].fields[2]: co2 is listed twice",
    "profiles-disagree": "2: buses[0].port: the devices' profiles disagree on the baud rate "
                         "(4800 (net-irnet-pro), 9600 (huiwen-aq)); set baudrate for the bus",
    "duplicate-name": "9: buses[1].devices[0].name: device name 'tank' is already used at "
                      "line 5",
    "same-port": "7: buses[1].port: port /dev/ttyUSB0 is already used by bus 'north' (line 2); "
                 "put all its devices on one bus",
    "bad-gateway": "2: buses[0].port: 'tcp://10.0.0.5': expected tcp://HOST:PORT",
    "negative-interval": "6: buses[0].devices[0].interval: -1 s is outside 0..86400 s "
                         "(0: as fast as the bus allows)",
    "out-of-range": "5: buses[0].devices[0].address: 241 is outside this device's range 1..240",
    "broadcast": "5: buses[0].devices[0].address: 0 is the broadcast address",
    "no-devices": "3: buses[0].devices: no devices: a bus needs at least one",
    "syntax": "5: YAML syntax: did not find expected ',' or '}'",
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_a_broken_site_is_refused_with_file_line_path_and_reason(name: str) -> None:
    path = SITE / f"{name}.yaml"
    with pytest.raises(ConfigError) as err:
        load_site(path)
    assert str(err.value) == f"{path}:{BROKEN[name]}"
    assert err.value.exit_code == 2


def test_a_missing_profile_directory_is_named_with_its_resolved_path() -> None:
    with pytest.raises(ConfigError) as err:
        load_site(SITE / "missing-profile-dir.yaml")
    assert str(err.value) == (f"{SITE / 'missing-profile-dir.yaml'}:1: profiles[0]: profile "
                              f"directory {SITE / 'no-such-dir'} does not exist")


def test_a_missing_site_file_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read"):
        load_site(SITE / "nope.yaml")


# -- ad-hoc devices from the command line ------------------------------------


def test_ad_hoc_devices_take_serial_settings_from_their_profiles() -> None:
    site = from_specs("/dev/ttyUSB0", [("huiwen-aq", 3), ("radar-level", 5)], interval=0.5)
    (bus,) = site.buses
    assert (bus.port, bus.serial_text) == ("/dev/ttyUSB0", "9600 8N1")
    assert [(d.name, d.interval) for d in bus.devices] == [("huiwen-aq@3", 0.5),
                                                          ("radar-level@5", 0.5)]


def test_ad_hoc_fields_apply_to_each_device_that_has_them() -> None:
    site = from_specs("/dev/ttyUSB0", [("huiwen-aq", 3), ("co2meter-an117", 7)],
                      baudrate=115200, fields=["co2", "temperature"])
    air, co2 = site.buses[0].devices
    assert [f.name for f in air.fields] == ["co2", "temperature"]
    assert [f.name for f in co2.fields] == ["co2"]


@pytest.mark.parametrize(("specs", "kwargs", "message"), [
    ([("net-irnet-pro", 1), ("huiwen-aq", 3)], {},
     "the devices' profiles disagree on the baud rate (4800 (net-irnet-pro), 9600 (huiwen-aq)); "
     "give --baudrate for the bus"),
    ([("huiwen-aq", 3), ("radar-level", 3)], {},
     "radar-level@3: address 3 is already used by huiwen-aq@3"),
    ([("huiwen-aq", 3)], {"baudrate": 19200},
     "huiwen-aq@3: huiwen-aq cannot run at 19200 baud, the speed of bus /dev/ttyUSB0 (set by "
     "--baudrate); it supports 4800, 9600, 115200"),
    ([("co2meter-an117", 254), ("radar-level", 1)], {"baudrate": 115200},
     "co2meter-an117@254: 254 (0xFE) is the 'any device' address of co2meter-an117: every such "
     "device answers it, so it only works alone on a bus, and /dev/ttyUSB0 has 2 devices"),
    ([("huiwen-aq", 3)], {"fields": ["co3"]},
     "--fields: no device here has a field 'co3' (did you mean 'co2'?)"),
    ([("huiwen-aq", 3), ("radar-level", 4)], {"fields": ["co2"]},
     "radar-level@4 has none of the fields co2 (its fields: air_gap_cm, air_gap_mm, level_cm, "
     "level_mm, status, range_cm, blind_zone_cm, slave_address, baud_rate)"),
    ([], {}, "name at least one device, PROFILE@ADDRESS (e.g. net-irnet-pro@1)"),
])
def test_ad_hoc_mistakes_are_usage_errors(specs: list[tuple[str, int]],
                                          kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(RtupollError) as err:
        from_specs("/dev/ttyUSB0", specs, **kwargs)  # type: ignore[arg-type]
    assert isinstance(err.value, UsageError)
    assert str(err.value) == message


def test_the_simulator_serves_any_device_at_any_speed() -> None:
    site = from_specs("/dev/pts/9", [("net-irnet-pro", 1), ("co2meter-an117", 2)],
                      baudrate=9600, check_serial=False)
    assert site.buses[0].serial_text == "9600 8N1"
    with pytest.raises(UsageError, match="cannot run at 9600 baud"):
        from_specs("/dev/pts/9", [("net-irnet-pro", 1), ("co2meter-an117", 2)], baudrate=9600)


def test_a_gateway_url_is_read_as_the_bus_reads_it() -> None:
    from rtupoll.config.site import from_specs

    # the scheme is case-insensitive for the bus, so it must be for the site checks too
    with pytest.raises(UsageError, match=r"'TCP://gw': expected tcp://HOST:PORT"):
        from_specs("TCP://gw", [("huiwen-aq", 1)])


def test_idle_gap_per_device_and_per_bus_over_the_profiles(tmp_path: Path) -> None:
    mine = tmp_path / "slow-meter.yaml"
    base = (Path(__file__).parents[2] / "profiles" / "radar-level.yaml").read_text()
    mine.write_text(base.replace("id: radar-level", "id: slow-meter").replace(
        "limits:", "limits:\n  idle_gap: 0.85", 1))
    site = tmp_path / "site.yaml"
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n    idle_gap: 0.01\n    devices:\n"
                    "      - {profile: slow-meter.yaml, address: 1}\n"
                    "      - {profile: slow-meter.yaml, address: 2, idle_gap: 0.05}\n"
                    "      - {profile: huiwen-aq, address: 3}\n")
    (bus,) = load_site(site).buses
    assert bus.idle_gap == 0.01
    assert [d.gap for d in bus.devices] == [0.85, 0.05, 0.0]  # profile, own, none
    site.write_text(site.read_text().replace("idle_gap: 0.05", "idle_gap: 12"))
    with pytest.raises(ConfigError, match=r"site.yaml:6: buses\[0\].devices\[1\].idle_gap: "
                                          r"12 s is outside 0..10 s"):
        load_site(site)


def test_ad_hoc_idle_gap_replaces_the_profiles() -> None:
    site = from_specs("/dev/ttyUSB0", [("huiwen-aq", 3), ("huiwen-aq", 4)], idle_gap=0.05)
    assert [d.gap for d in site.buses[0].devices] == [0.05, 0.05]
