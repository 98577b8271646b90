"""A corpus of Home Assistant and Telegraf configurations, imported and then polled.

Each configuration is written here from a table of entities (type, byte order, scale,
the raw value the device holds). A responder (``import_peers.Responder``) holds each
value encoded as the source tool reads it; rtupoll imports the configuration, polls the
responder with the imported site file, and every field must read what Home Assistant or
Telegraf would show for the same registers (``import_peers`` decodes as they do).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import pytest
import yaml
from cli_runner import rtupoll
from conftest import ANSWERED
from import_peers import (
    TG_FORMATS,
    Responder,
    ha_encode,
    ha_shows,
    tg_decode,
    tg_encode,
)

HA_VALUES: dict[str, int | float | str] = {
    "int16": -1234, "uint16": 54321, "int32": -123456789, "uint32": 3_000_000_000,
    "int64": -1_234_567_890_123, "uint64": 12_345_678_901_234_567, "float32": -20.5,
    "float64": 1234.5678125, "string": "SN-0042",
}
WIDE = {"int32", "uint32", "int64", "uint64", "float32", "float64"}
COUNT = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "int64": 4, "uint64": 4,
         "float32": 2, "float64": 4, "string": 4}


def poll_site(out: Path, device: Responder) -> dict[tuple[str, str], Any]:
    """Point every bus of the imported site at the responder; poll once; values by
    (device, field)."""
    site = yaml.safe_load((out / "site.yaml").read_text(encoding="utf-8"))
    for bus in site["buses"]:
        bus["port"] = f"tcp://127.0.0.1:{device.port()}"
        for each in bus["devices"]:  # (the responder answers: a wait that ends)
            each["timeout"] = ANSWERED
    (out / "site.yaml").write_text(yaml.safe_dump(site, allow_unicode=True), encoding="utf-8")
    done = rtupoll("poll", "-c", str(out / "site.yaml"), "--once", "--format", "json",
                   cwd=out)
    assert done.returncode == 0, done.stderr
    records = [json.loads(line) for line in done.stdout.splitlines()]
    assert all(r["status"] == "ok" for r in records), [r for r in records
                                                        if r["status"] != "ok"]
    return {(r["device"], r["field"]): r["value"] for r in records}


def close(got: Any, want: Any, precision: int = 6) -> bool:
    if isinstance(want, str) or isinstance(got, (str, bool)):
        return bool(got == want)
    return math.isclose(float(got), float(want), rel_tol=1e-6,
                        abs_tol=0.5 * 10 ** -precision + 1e-9)


# -- Home Assistant --------------------------------------------------------------------

def ha_entities() -> list[dict[str, Any]]:
    """Every data type with every swap Home Assistant allows for it, plus scale, offset
    and precision, two names that differ only in Cyrillic letters, and a once-read one."""
    out: list[dict[str, Any]] = []
    address = 0
    for dtype, raw in HA_VALUES.items():
        swaps = ["none", "byte", "word", "word_byte"] if dtype in WIDE else ["none", "byte"]
        for swap in swaps:
            conf: dict[str, Any] = {"name": f"{dtype} {swap}", "slave": 1, "address": address,
                                    "input_type": "holding", "data_type": dtype,
                                    "scan_interval": 5}
            if dtype == "string":
                conf["count"] = COUNT[dtype]
            if swap != "none":
                conf["swap"] = swap
            if dtype.startswith("float"):
                conf["precision"] = 3
            out.append({"conf": conf, "raw": raw})
            address += COUNT[dtype]
    out.append({"conf": {"name": "Temperature", "slave": 2, "address": 1,
                         "input_type": "input", "data_type": "int16", "scale": 0.1,
                         "offset": -40, "precision": 1, "unit_of_measurement": "°C"},
                "raw": 655})
    out.append({"conf": {"name": "Счётчик ГВС", "slave": 2, "address": 2,
                         "input_type": "input", "data_type": "uint32",
                         "unit_of_measurement": "m³"}, "raw": 123456})
    out.append({"conf": {"name": "Счётчик ХВС", "slave": 2, "address": 4,  # noqa: RUF001
                         "input_type": "input", "data_type": "uint32",
                         "unit_of_measurement": "m³"}, "raw": 654321})
    out.append({"conf": {"name": "Serial number", "slave": 2, "address": 10,
                         "input_type": "input", "data_type": "uint32", "scan_interval": 0},
                "raw": 777})
    return out


def ha_corpus(tmp: Path) -> Path:
    """configuration.yaml: the hub's port a secret, its sensors in an included file, its
    binary sensors in another; slave 2's sensors in a folder (``room/``) for a second
    hub to merge as a list."""
    entities = ha_entities()
    (tmp / "secrets.yaml").write_text("modbus_port: /dev/ttyUSB7\n", encoding="utf-8")
    one = [e["conf"] for e in entities if e["conf"]["slave"] == 1]
    two = [e["conf"] for e in entities if e["conf"]["slave"] == 2]
    (tmp / "meter.yaml").write_text(yaml.safe_dump(one, allow_unicode=True), encoding="utf-8")
    (tmp / "room").mkdir()
    (tmp / "room" / "a.yaml").write_text(yaml.safe_dump(two[:2], allow_unicode=True),
                                         encoding="utf-8")
    (tmp / "room" / "b.yaml").write_text(yaml.safe_dump(two[2:], allow_unicode=True),
                                         encoding="utf-8")
    (tmp / "binary.yaml").write_text(
        "- {name: Door, slave: 2, address: 0, input_type: coil}\n"
        "- {name: Alarm, slave: 2, address: 20, input_type: holding}\n", encoding="utf-8")
    config = tmp / "configuration.yaml"
    config.write_text(
        "homeassistant:\n  name: Home\n"
        "modbus:\n"
        "  - name: Meter Bus\n    type: serial\n    method: rtu\n"
        "    port: !secret modbus_port\n    baudrate: 9600\n    bytesize: 8\n"
        "    parity: E\n    stopbits: 1\n    timeout: 2\n    retries: 1\n"
        "    message_wait_milliseconds: 30\n"
        "    sensors: !include meter.yaml\n"
        "    binary_sensors: !include binary.yaml\n", encoding="utf-8")
    return config


def test_a_home_assistant_corpus_reads_what_home_assistant_shows(tmp_path: Path) -> None:
    src = tmp_path / "ha"
    src.mkdir()
    config = ha_corpus(src)
    # slave 2's sensors live in a folder: a second hub entry on the same port includes it
    config.write_text(config.read_text(encoding="utf-8") +
                      "  - name: Room Bus\n    type: rtuovertcp\n    host: 127.0.0.1\n"
                      "    port: 1502\n    sensors: !include_dir_merge_list room\n",
                      encoding="utf-8")
    out = tmp_path / "out"
    done = rtupoll("profiles", "import", str(config), "-o", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    notes = done.stderr
    assert "/dev/ttyUSB7" not in notes  # a secret's value is never printed
    assert "message_wait_milliseconds" in notes and "3.5-character" in notes
    assert "'Serial number': scan_interval 0: read once at start" in notes
    site = yaml.safe_load((out / "site.yaml").read_text(encoding="utf-8"))
    meter = site["buses"][0]
    assert meter["port"] == "/dev/ttyUSB7" and meter["parity"] == "E"
    assert meter["devices"][0]["timeout_ceiling"] == 2 and meter["devices"][0]["retries"] == 1
    room = yaml.safe_load((out / "ha-room-bus-2.yaml").read_text(encoding="utf-8"))
    names = {f["name"]: f for f in room["fields"]}
    assert "schyotchik_gvs" in names and "schyotchik_khvs" in names  # apart, in ASCII
    assert names["schyotchik_gvs"]["description"] == "Счётчик ГВС"
    assert names["serial_number"]["interval"] == "once"
    with Responder() as device:
        expected: dict[tuple[str, str], tuple[Any, int]] = {}
        for e in ha_entities():
            conf = e["conf"]
            regs = ha_encode(e["raw"], conf["data_type"], conf.get("swap", "none"),
                             conf.get("count", 1))
            fc = 3 if conf["input_type"] == "holding" else 4
            device.set(conf["slave"], fc, conf["address"], regs)
            dev = "meter-bus-1" if conf["slave"] == 1 else "room-bus-2"
            profile = yaml.safe_load((out / f"ha-{dev}.yaml").read_text(encoding="utf-8"))
            field = next(f["name"] for f in profile["fields"]
                         if f["address"] == conf["address"])
            expected[dev, field] = (ha_shows(regs, conf), conf.get("precision", 0))
        device.set(2, 1, 0, [1])         # the door is open
        device.set(2, 3, 20, [0x0003])   # bit 0 of the alarm register set
        got = poll_site(out, device)
    for key, (want, precision) in expected.items():
        assert close(got[key], want, precision), (key, got[key], want)
    assert got["meter-bus-2", "door"] is True and got["meter-bus-2", "alarm"] in (1, True)


def test_the_form_before_2021_converts_with_the_same_meaning(tmp_path: Path) -> None:
    config = tmp_path / "configuration.yaml"
    config.write_text(
        "modbus:\n  name: hub1\n  type: serial\n  method: rtu\n  port: /dev/ttyUSB0\n"
        "  baudrate: 9600\n  stopbits: 1\n  bytesize: 8\n  parity: N\n"
        "sensor:\n"
        "  - platform: template\n    sensors: {}\n"
        "  - platform: modbus\n    scan_interval: 10\n    registers:\n"
        "      - {name: Power, hub: hub1, slave: 3, register: 0, register_type: input,\n"
        "         data_type: float, count: 2, reverse_order: true, precision: 1}\n"
        "      - {name: Energy, hub: hub1, slave: 3, register: 2, register_type: input,\n"
        "         data_type: uint, count: 2, scale: 0.01, precision: 2}\n"
        "      - {name: Temp, hub: hub1, slave: 3, register: 4, data_type: int,\n"
        "         count: 1, reverse_order: true, scale: 0.1, precision: 1}\n"
        "binary_sensor:\n  - platform: modbus\n    inputs:\n"
        "      - {name: Run, hub: hub1, slave: 3, address: 7, input_type: coil}\n",
        encoding="utf-8")
    out = tmp_path / "out"
    done = rtupoll("profiles", "import", str(config), "-o", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("1 profile(s), 4 field(s)")
    site = yaml.safe_load((out / "site.yaml").read_text(encoding="utf-8"))
    assert site["buses"][0]["devices"][0]["interval"] == 10
    confs = {"power": ({"data_type": "float", "count": 2, "reverse_order": True,
                        "precision": 1}, 4, 0, -1532.25),
             "energy": ({"data_type": "uint", "count": 2, "scale": 0.01, "precision": 2},
                        4, 2, 123456),
             "temp": ({"data_type": "int", "count": 1, "scale": 0.1, "precision": 1},
                      3, 4, -55)}
    with Responder() as device:
        for conf, fc, address, raw in confs.values():
            dtype = {"float": "float32", "uint": "uint32", "int": "int16"}[conf["data_type"]]
            swap = "word" if conf.get("reverse_order") else "none"
            device.set(3, fc, address, ha_encode(raw, dtype, swap, conf["count"]))
        device.set(3, 1, 7, [1])
        got = poll_site(out, device)
    for name, (conf, _fc, _address, raw) in confs.items():
        dtype = {"float": "float32", "uint": "uint32", "int": "int16"}[conf["data_type"]]
        regs = ha_encode(raw, dtype, "word" if conf.get("reverse_order") else "none",
                         conf["count"])
        assert close(got["hub1-3", name], ha_shows(regs, conf), conf["precision"]), name
    assert got["hub1-3", "run"] is True


def test_an_include_that_is_missing_names_the_file_and_line(tmp_path: Path) -> None:
    config = tmp_path / "configuration.yaml"
    config.write_text("modbus:\n  - name: hub\n    port: /dev/ttyUSB0\n"
                      "    sensors: !include sdm630.yaml\n", encoding="utf-8")
    done = rtupoll("profiles", "import", str(config), "-o", str(tmp_path / "o"), cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip() == (f"rtupoll: {config}:4: modbus[0].sensors: !include "
                                   f"sdm630.yaml: no such file ({tmp_path / 'sdm630.yaml'})")
    assert not (tmp_path / "o").exists()


def test_a_missing_secret_is_named_and_never_guessed(tmp_path: Path) -> None:
    config = tmp_path / "configuration.yaml"
    config.write_text("modbus:\n  - name: hub\n    port: !secret rs485\n"
                      "    sensors: [{name: x, slave: 1, address: 0}]\n", encoding="utf-8")
    done = rtupoll("profiles", "import", str(config), "-o", str(tmp_path / "o"), cwd=tmp_path)
    assert done.returncode == 2
    assert "!secret rs485: not found in secrets.yaml" in done.stderr
    assert done.stderr.count("\n") == 1


# -- Telegraf --------------------------------------------------------------------------

TG_VALUES = {"INT16": -1234, "UINT16": 54321, "INT32": -123456789, "UINT32": 3_000_000_000,
             "INT64": -1_234_567_890_123, "UINT64": 12_345_678_901_234_567,
             "FLOAT32": -20.5, "FLOAT64": 1234.5678125}
ORDERS = ("ABCD", "DCBA", "BADC", "CDAB")


def tg_request_fields() -> list[dict[str, Any]]:
    """Every numeric type in every byte order (one request per order, slave 11-14)."""
    out = []
    for k, order in enumerate(ORDERS):
        address = 0
        for dtype, value in TG_VALUES.items():
            words = struct.calcsize(TG_FORMATS[dtype]) // 2
            scale = 0.1 if dtype in ("INT32", "UINT16") else None
            out.append({"slave": 11 + k, "order": order, "type": dtype, "address": address,
                        "value": value, "scale": scale,
                        "name": f"{dtype.lower()} {order.lower()}"})
            address += words
    return out


def tg_config(tmp: Path) -> Path:
    lines = ['[agent]\n  interval = "10s"\n',
             '[[inputs.modbus]]\n  name = "Meters"\n  controller = "file:///dev/ttyUSB0"\n'
             '  baud_rate = 9600\n  configuration_type = "request"\n  interval = "900s"\n'
             '  pause_between_requests = "20ms"\n']
    for k, order in enumerate(ORDERS):
        fields = []
        for f in tg_request_fields():
            if f["order"] != order:
                continue
            scale = f", scale = {f['scale']}" if f["scale"] else ""
            fields.append(f'    {{ address = {f["address"]}, name = "{f["name"]}", '
                          f'type = "{f["type"]}"{scale} }},')
        lines.append(f'  [[inputs.modbus.request]]\n    slave_id = {11 + k}\n'
                     f'    byte_order = "{order}"\n    register = "holding"\n'
                     f'    fields = [\n' + "\n".join(fields) + "\n    ]\n")
    lines.append('  [[inputs.modbus.request]]\n    slave_id = 15\n    register = "input"\n'
                 '    fields = [\n'
                 '      { address = 0, name = "hi", type = "UINT8H" },\n'
                 '      { address = 0, name = "lo", type = "INT8L" },\n'
                 '      { address = 1, name = "flag", type = "BIT", bit = 5 },\n'
                 '      { address = 2, name = "plain", type = "UINT16", scale = 0.0 },\n'
                 '      { address = 3, name = "whole", type = "UINT16", scale = 0.5, '
                 'output = "INT64" },\n'
                 '      { address = 4, name = "serial", type = "STRING", length = 4 },\n'
                 '    ]\n')
    lines.append('  [[inputs.modbus.request]]\n    slave_id = 18\n    register = "holding"\n'
                 '    byte_order = "DCBA"\n    fields = [\n'
                 '      { address = 0, name = "model", type = "STRING", length = 3 },\n    ]\n')
    lines.append('[[inputs.modbus]]\n  name = "Probe"\n  controller = "file:///dev/ttyUSB1"\n'
                 '  configuration_type = "metric"\n'
                 '  [[inputs.modbus.metric]]\n    slave_id = 16\n    byte_order = "CDAB"\n'
                 '    measurement = "probe"\n    fields = [\n'
                 '      { register = "input", address = 0, name = "temp", type = "FLOAT32" },\n'
                 '      { register = "holding", address = 4, name = "level", type = "INT16",'
                 ' scale = 0.01 },\n    ]\n')
    lines.append('[[inputs.modbus]]\n  name = "Old"\n  controller = "file:///dev/ttyUSB2"\n'
                 '  slave_id = 17\n'
                 '  holding_registers = [\n'
                 '    { name = "volts", byte_order = "AB", data_type = "FIXED", scale = 0.1,'
                 ' address = [0] },\n'
                 '    { name = "amps", byte_order = "BA", data_type = "UFIXED", scale = 0.01,'
                 ' address = [1] },\n'
                 '    { name = "energy", byte_order = "CDAB", data_type = "FLOAT32-IEEE",'
                 ' scale = 1.0, address = [2, 3] },\n'
                 '    { name = "count", byte_order = "GHEFCDAB", data_type = "UFIXED",'
                 ' scale = 1.0, address = [4, 5, 6, 7] },\n  ]\n'
                 '  coils = [ { name = "pump", address = [3] } ]\n')
    path = tmp / "telegraf.conf"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def _string_regs(text: bytes, order: str) -> list[int]:
    """Telegraf's strings: each register in the request's 16-bit byte order."""
    pairs = [text[i:i + 2] for i in range(0, len(text), 2)]
    return [int.from_bytes(p if order == "AB" else p[::-1], "big") for p in pairs]


def test_a_telegraf_corpus_reads_what_telegraf_shows(tmp_path: Path) -> None:
    config = tg_config(tmp_path)
    out = tmp_path / "out"
    done = rtupoll("profiles", "import", str(config), "-o", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "pause_between_requests" in done.stderr  # listed, not dropped
    assert "'whole': output INT64" in done.stderr
    site = yaml.safe_load((out / "site.yaml").read_text(encoding="utf-8"))
    intervals = {d["name"]: d["interval"] for b in site["buses"] for d in b["devices"]}
    assert intervals["meters-11"] == 900       # the plugin's own interval
    assert intervals["probe-16"] == 10         # the agent's
    expected: dict[tuple[str, str], Any] = {}
    with Responder() as device:
        for f in tg_request_fields():
            fmt = TG_FORMATS[f["type"]]
            regs = tg_encode(f["value"], fmt, f["order"])
            device.set(f["slave"], 3, f["address"], regs)
            shown = tg_decode(regs, fmt, f["order"]) * (f["scale"] or 1)
            expected[f"meters-{f['slave']}", f["name"].replace(" ", "_")] = shown
        device.set(15, 4, 0, [0xF2A5, 1 << 5, 321, 7, *_string_regs(b"SN-0042\0", "AB")])
        device.set(18, 3, 0, _string_regs(b"EM24X\0", "BA"))
        expected.update({("meters-15", "hi"): 0xF2, ("meters-15", "lo"): -0x5B,
                         ("meters-15", "flag"): 1, ("meters-15", "plain"): 321,
                         ("meters-15", "whole"): 3.5, ("meters-15", "serial"): "SN-0042",
                         ("meters-18", "model"): "EM24X"})
        device.set(16, 4, 0, tg_encode(-3.25, "f", "CDAB"))
        device.set(16, 3, 4, tg_encode(-1234, "h", "CDAB"))
        expected.update({("probe-16", "temp"): -3.25, ("probe-16", "level"): -12.34})
        device.set(17, 3, 0, tg_encode(-123, "h", "AB") + tg_encode(4000, "H", "BA")
                   + tg_encode(17.5, "f", "CDAB") + tg_encode(2**40 + 5, "Q", "GHEFCDAB"))
        device.set(17, 1, 3, [1])
        expected.update({("old-17", "volts"): -12.3, ("old-17", "amps"): 40.0,
                         ("old-17", "energy"): 17.5, ("old-17", "count"): 2**40 + 5,
                         ("old-17", "pump"): True})
        got = poll_site(out, device)
    for key, want in expected.items():
        precision = 0 if key == ("meters-15", "whole") else 6
        assert close(got[key], want, precision), (key, got[key], want)


def test_an_unknown_configuration_type_is_named_as_written(tmp_path: Path) -> None:
    path = tmp_path / "telegraf.conf"
    path.write_text('[[inputs.modbus]]\n  name = "x"\n  controller = "file:///dev/ttyUSB0"\n'
                    '  configuration_type = "requests"\n', encoding="utf-8")
    done = rtupoll("profiles", "import", str(path), "-o", str(tmp_path / "o"), cwd=tmp_path)
    assert done.returncode == 2
    assert "configuration_type 'requests' (Telegraf knows register, request and metric)" \
        in done.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["Температура", "température", "温度"])
def test_a_name_in_any_script_keeps_its_spelling(tmp_path: Path, name: str) -> None:
    config = tmp_path / "configuration.yaml"
    config.write_text(f"modbus:\n  - name: hub\n    port: /dev/ttyUSB0\n    sensors:\n"
                      f"      - {{name: {name}, slave: 1, address: 0}}\n"
                      f"      - {{name: {name} 2, slave: 1, address: 1}}\n", encoding="utf-8")
    out = tmp_path / "o"
    done = rtupoll("profiles", "import", str(config), "-o", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    fields = yaml.safe_load((out / "ha-hub-1.yaml").read_text(encoding="utf-8"))["fields"]
    assert [f["description"] for f in fields] == [name, f"{name} 2"]
    assert len({f["name"] for f in fields}) == 2


SHADOW = "root:$y$j9T$Qm1Mv3hashhashhash:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n"


@pytest.mark.parametrize("how", ["relative", "absolute", "link in a folder", "secrets link"])
def test_an_include_outside_the_configurations_folder_is_one_line_and_never_read(
        tmp_path: Path, how: str) -> None:
    """An HA configuration from a forum is untrusted: its includes stay in its folder."""
    outside = tmp_path / "etc" / "shadow"
    outside.parent.mkdir()
    outside.write_text(SHADOW, encoding="utf-8")
    conf = tmp_path / "ha"
    (conf / "room").mkdir(parents=True)
    hub = "modbus:\n  - name: hub\n    port: /dev/ttyUSB0\n"
    sensors = "    sensors: [{name: x, slave: 1, address: 0}]\n"
    line, tag = 4, {"relative": "!include ../etc/shadow",
                    "absolute": f"!include {outside}",
                    "link in a folder": "!include_dir_merge_list room: evil.yaml links",
                    "secrets link": "!secret rs485: secrets.yaml links"}[how]
    if how in ("relative", "absolute"):
        text = hub + f"    sensors: {tag.split(' ', 1)[0]} {tag.split(' ', 1)[1]}\n"
    elif how == "link in a folder":
        (conf / "room" / "evil.yaml").symlink_to(outside)
        text = hub + "    sensors: !include_dir_merge_list room\n"
    else:
        (conf / "secrets.yaml").symlink_to(outside)
        text = "modbus:\n  - name: hub\n    port: !secret rs485\n" + sensors
        line = 3
    config = conf / "configuration.yaml"
    config.write_text(text, encoding="utf-8")
    done = rtupoll("profiles", "import", str(config), "-o", str(tmp_path / "o"), cwd=tmp_path)
    assert done.returncode == 2
    (message,) = done.stderr.splitlines()
    assert message.startswith(f"rtupoll: {config}:{line}: modbus[0].")
    assert f"{tag}" in message and "outside the configuration's folder" in message, message
    assert "19000" not in done.stderr + done.stdout and "daemon" not in done.stderr
    assert not (tmp_path / "o").exists()


def test_no_line_of_a_file_is_echoed_as_a_key(tmp_path: Path) -> None:
    """A file in the folder that is not YAML settings (a copy of some other file) is
    named by file:line in the notes, its lines never shown."""
    (tmp_path / "meter.yaml").write_text(SHADOW, encoding="utf-8")
    config = tmp_path / "configuration.yaml"
    config.write_text("modbus:\n  - name: hub\n    port: /dev/ttyUSB0\n"
                      "    extra: !include meter.yaml\n"
                      '    "root:$y$j9T$Qm1Mv3hash:19000:0:99999:7:::": 1\n'
                      "    sensors: [{name: x, slave: 1, address: 0}]\n", encoding="utf-8")
    done = rtupoll("profiles", "import", str(config), "-o", str(tmp_path / "o"), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "$y$" not in done.stderr and "19000" not in done.stderr, done.stderr
    assert f"{tmp_path / 'meter.yaml'}:1: not carried over: extra (" in done.stderr
    assert (f"{config}:5: modbus[0].?: not carried over: a key that is no "
            "setting's name (") in done.stderr
