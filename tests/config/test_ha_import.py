"""``rtupoll profiles import``: a Home Assistant ``modbus:`` configuration becomes
profiles and a site file; what cannot be converted is reported line by line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_runner import Ran
from cli_runner import rtupoll as run

from rtupoll.config.ha_import import import_ha
from rtupoll.config.library import load_profile
from rtupoll.config.site import load_site
from rtupoll.model.codec import ByteOrder
from rtupoll.sim.runner import simulated_bus

CONFIG = Path(__file__).parents[1] / "fixtures" / "ha" / "configuration.yaml"


@pytest.fixture(scope="module")
def imported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Ran]:
    out = tmp_path_factory.mktemp("ha")
    return out, run("profiles", "import", str(CONFIG), "-o", str(out))


def test_each_slave_of_each_rtu_hub_becomes_a_profile(imported: tuple[Path, Ran]) -> None:
    out, result = imported
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in out.iterdir()) == [
        "ha-gateway-4.yaml", "ha-meter-bus-1.yaml", "ha-meter-bus-2.yaml",
        "ha-meter-bus-3.yaml", "site.yaml"]
    assert result.stdout.startswith(f"4 profile(s), 13 field(s) written to {out}/; 8 note(s)")


def test_what_was_not_converted_is_reported_line_by_line(imported: tuple[Path, Ran]
                                                         ) -> None:
    every = imported[1].stderr.splitlines()
    lines = [line for line in every if not line.startswith("warning: ")]
    where = [line.split(": ", 2)[:2] for line in lines]
    assert where == [
        [f"{CONFIG}:46", "modbus[0].sensors[3].address"],      # overlaps energy_import
        [f"{CONFIG}:65", "modbus[0].sensors[5].min_value"],    # HA clamps
        [f"{CONFIG}:66", "modbus[0].sensors[5].max_value"],
        [f"{CONFIG}:69", "modbus[0].sensors[6].address"],      # 40001: a 1-based habit
        [f"{CONFIG}:83", "modbus[0].sensors[8].data_type"],    # custom struct
        [f"{CONFIG}:90", "modbus[0].sensors[9].swap"],         # word swap on 16 bits
        [f"{CONFIG}:108", "modbus[0].switches"],
        [f"{CONFIG}:123", "modbus[2].type"],                   # Modbus TCP, not RTU
    ]
    assert "reads the registers of 'energy_import'" in lines[0]
    assert "If the manual means register 1, use 0" in lines[3]
    assert "data_type custom (a struct format) has no rtupoll equivalent" in lines[4]
    # then each profile written says it is unverified (nobody checked it against a
    # vendor's document), once
    assert [line.split(" is unverified (no provenance): ")[0]
            for line in every[len(lines):]] == [
        f"warning: profile {pid}" for pid in
        ("ha-meter-bus-1", "ha-meter-bus-2", "ha-meter-bus-3", "ha-gateway-4")]


def test_swap_types_scale_and_counters_carry_over(imported: tuple[Path, Ran]) -> None:
    out = imported[0]
    meter = load_profile(out / "ha-meter-bus-1.yaml")
    assert meter.names() == ["grid_voltage", "grid_power", "energy_import"]
    assert meter.field("grid_voltage").layout.order is ByteOrder.ABCD
    assert meter.field("grid_power").layout.order is ByteOrder.CDAB          # swap: word
    assert meter.field("grid_voltage").precision == 1
    energy = meter.field("energy_import")
    assert energy.counter and energy.unit == "kWh" and energy.interval == 60
    assert meter.field("grid_power").interval is None  # the device's own rate (5 s)
    room = load_profile(out / "ha-meter-bus-2.yaml")
    temp = room.field("room_temperature")
    assert temp.layout.scale == 0.1 and -32768 in temp.sentinels            # nan_value
    inverter = load_profile(out / "ha-meter-bus-3.yaml")
    pv = inverter.field("pv_power")
    assert (pv.address, pv.layout.order) == (40001, ByteOrder.DCBA)          # word_byte
    assert inverter.field("inverter_serial").words == 5
    assert [f.name for f in inverter.fields if f.name.startswith("string_currents")] == \
        ["string_currents_1", "string_currents_2", "string_currents_3"]      # slave_count 2
    assert inverter.field("string_currents_3").address == 72
    assert inverter.field("alarm_bit").layout.width == 1                     # register bit 0
    assert inverter.field("inverter_running").table.value == "coil"


def test_the_site_file_loads_with_every_hub_and_slave(imported: tuple[Path, Ran]) -> None:
    site = load_site(imported[0] / "site.yaml")
    devices = {(b.name, b.port, d.address, d.interval) for b, d in site.devices()}
    assert devices == {("meter-bus", "/dev/ttyUSB0", 1, 5), ("meter-bus", "/dev/ttyUSB0", 2, 15),
                       ("meter-bus", "/dev/ttyUSB0", 3, 15),
                       ("gateway", "tcp://192.168.1.50:4196", 4, 15)}


def test_an_imported_profile_polls_against_the_simulator(imported: tuple[Path, Ran]
                                                         ) -> None:
    out = imported[0]
    with simulated_bus(["ha-meter-bus-2@2"], tcp=True, profile_dirs=[out], tick=None) as bus:
        result = run("poll", "--profiles", str(out), "--port", bus.port, "--once",
                     "--format", "json", "ha-meter-bus-2@2")
    assert result.returncode == 0, result.stderr
    recs = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(r["field"], r["status"]) for r in recs] == [("room_temperature", "ok"),
                                                          ("room_humidity", "ok")]


def test_a_file_with_nothing_to_convert_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "configuration.yaml"
    path.write_text("modbus:\n  - name: plc\n    type: tcp\n    host: 10.0.0.1\n"
                    "    sensors: [{name: x, slave: 1, address: 0}]\n", encoding="utf-8")
    result = run("profiles", "import", str(path), "-o", str(tmp_path / "out"))
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        f"{path}:3: modbus[0].type: not converted: hub 'plc' is type tcp (Modbus TCP/UDP); "
        "rtupoll speaks RTU, over a serial port or an RTU-over-TCP gateway",
        f"rtupoll: {path}: nothing could be converted"]
    assert not (tmp_path / "out").exists()


def test_a_config_without_modbus_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "configuration.yaml"
    path.write_text("homeassistant:\n  name: Home\n", encoding="utf-8")
    result = run("profiles", "import", str(path))
    assert result.returncode == 2
    assert result.stderr.strip() == f"rtupoll: {path}:1: no 'modbus:' section"


def test_the_hub_list_alone_converts_too(tmp_path: Path) -> None:
    path = tmp_path / "modbus.yaml"
    path.write_text("- name: hub\n  type: serial\n  port: /dev/ttyUSB1\n  baudrate: 19200\n"
                    "  parity: E\n  sensors:\n"
                    "    - {name: Level, slave: 7, address: 3, data_type: uint16}\n",
                    encoding="utf-8")
    result = import_ha(path)
    assert list(result.profiles) == ["ha-hub-7"] and result.report == []
    assert "baudrate: 19200" in result.profiles["ha-hub-7"]
    assert "parity: E" in result.site


TELEGRAF = Path(__file__).parents[1] / "fixtures" / "telegraf" / "telegraf.conf"


def test_a_telegraf_request_style_configuration_converts_too(tmp_path: Path) -> None:
    result = run("profiles", "import", str(TELEGRAF), "-o", str(tmp_path))
    assert result.returncode == 0, result.stderr
    every = result.stderr.splitlines()
    assert [line.split(": ", 2)[:2] for line in every[:3]] == [
        [f"{TELEGRAF}:23", "inputs.modbus[0].request[0].fields[3]"],  # overlaps a u32
        [f"{TELEGRAF}:33", "inputs.modbus[0].request[1].fields[3]"],  # FLOAT16
        [f"{TELEGRAF}:46", "inputs.modbus[1]"],                       # Modbus TCP
    ]                                                   # (the register style converts)
    # then each profile written says it is unverified, once
    assert [line.split(" is unverified (no provenance): ")[0] for line in every[3:]] == [
        f"warning: profile {pid}" for pid in
        ("telegraf-plant-bus-1", "telegraf-plant-bus-2", "telegraf-old-1")]
    meter = load_profile(tmp_path / "telegraf-plant-bus-1.yaml")
    assert meter.names() == ["voltage", "current", "energy_import"]
    assert meter.field("voltage").layout.order is ByteOrder.CDAB
    assert meter.field("energy_import").layout.scale == 0.01
    probe = load_profile(tmp_path / "telegraf-plant-bus-2.yaml")
    assert probe.names() == ["temperature", "humidity", "address", "baud", "alarm", "relay"]
    assert (probe.field("address").layout.byte, probe.field("baud").layout.byte) == \
        ("high", "low")
    assert (probe.field("alarm").layout.shift, probe.field("alarm").layout.width) == (3, 1)
    site = load_site(tmp_path / "site.yaml")
    assert {(b.port, b.baudrate, b.parity, d.address, d.interval)
            for b, d in site.devices()} == {("/dev/ttyUSB0", 19200, "E", 1, 30),
                                            ("/dev/ttyUSB0", 19200, "E", 2, 30),
                                            ("/dev/ttyUSB1", 9600, "N", 1, 30)}
