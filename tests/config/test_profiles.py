"""The five seed profiles against their manuals' own frames."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from rtupoll import rtu
from rtupoll.config.library import load_library, load_one
from rtupoll.model.interpret import field_words, interpret
from rtupoll.model.profile import Addressing, Poll, Profile
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadRequest, WriteSingle

SEEDS = ("net-irnet-pro", "radar-level", "huiwen-aq", "co2meter-an117", "banner-ez-array")


def frame(text: str) -> bytes:
    return bytes.fromhex(text)


def decode_exchange(profile: Profile, request: bytes, response: bytes) -> dict[str, object]:
    """What a request/response pair carries, field by field, through the profile."""
    assert rtu.crc_ok(request), "request CRC"
    assert rtu.crc_ok(response), "response CRC"
    unit, function, start, count = struct.unpack(">BBHH", request[:6])
    assert response[0] == unit and response[1] == function and response[2] == 2 * count
    words = struct.unpack(f">{count}H", response[3 : 3 + 2 * count])
    table = {3: Table.HOLDING, 4: Table.INPUT}[function]
    values: dict[str, object] = {}
    for f in profile.fields:
        if f.table is table and start <= f.address and f.end <= start + count:
            values[f.name] = interpret(f, words[f.address - start : f.end - start]).value
    return values


GOLDEN = [
    ("net-irnet-pro", "01 04 00 06 00 02 91 CA", "01 04 04 00 00 A0 C1 42 14",
     {"concentration": -20.0}),
    ("net-irnet-pro", "01 03 02 00 00 02 C5 B3", "01 03 04 00 00 48 42 4C 02",
     {"calibration_gas_level": 50.0}),
    ("huiwen-aq", "01 04 75 36 00 05 CA 0B", "01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94",
     {"pm25": 25, "tvoc": 0.05, "hcho": 0.25, "co2": 5000}),
    # the manual prints byte count 06 here (its CRC covers the 06); 08 is right for 4 registers
    ("huiwen-aq", "01 04 75 54 00 04 AA 15", "01 04 08 00 01 00 01 00 02 00 00 A8 CD",
     {"pm25_level": "GOOD", "tvoc_level": "GOOD", "hcho_level": "MILD",
      "co2_level": "EXCELLENT"}),
    ("huiwen-aq", "01 03 9C 41 00 01 FA 4E", "01 03 02 00 01 79 84", {"slave_address": 1}),
    ("co2meter-an117", "FE 04 00 01 00 01 74 05", "FE 04 02 01 90 AC D8", {"co2": 400}),
    ("banner-ez-array", "41 03 9C 41 00 03 75 4F", "41 03 06 02 2B 00 00 00 64 34 B9",
     {"holding_40001": 555, "holding_40002": 0, "holding_40003": 100}),
]


@pytest.mark.parametrize(("pid", "request_hex", "response_hex", "expected"), GOLDEN)
def test_manual_frames_decode_to_the_manuals_values(pid: str, request_hex: str,
                                                    response_hex: str,
                                                    expected: dict[str, object]) -> None:
    values = decode_exchange(load_one(pid), frame(request_hex), frame(response_hex))
    assert values == expected


@pytest.mark.parametrize(("pid", "request_hex", "response_hex", "expected"), GOLDEN)
def test_our_requests_are_the_manuals_bytes(pid: str, request_hex: str, response_hex: str,
                                            expected: dict[str, object]) -> None:
    req = frame(request_hex)
    unit, function, start, count = struct.unpack(">BBHH", req[:6])
    table = {3: Table.HOLDING, 4: Table.INPUT}[function]
    assert ReadRequest(unit, table.read_function, start, count).frame() == req


def test_huiwen_manual_level_reply_has_a_wrong_byte_count() -> None:
    printed = frame("01 04 06 00 01 00 01 00 02 00 00 E4 AD")
    assert rtu.crc_ok(printed)  # consistent CRC ...
    assert printed[2] == 6 and len(printed) - 5 == 8  # ... but 8 data bytes, not 6


def test_huiwen_fifth_register_of_the_example_is_not_temperature() -> None:
    # The manual's example labels 30010 "temperature"; its register table says 30012.
    values = decode_exchange(load_one("huiwen-aq"), frame("01 04 75 36 00 05 CA 0B"),
                             frame("01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94"))
    assert "temperature" not in values
    assert load_one("huiwen-aq").field("temperature").address == 30012


@pytest.mark.parametrize(
    ("unit", "address", "crc"),
    [
        (1, 0, "C4 0B"), (1, 1, "95 CB"), (1, 2, "65 CB"), (1, 3, "34 0B"),
        (2, 0, "C4 38"), (2, 1, "95 F8"), (2, 2, "65 F8"), (2, 3, "34 38"),
        (3, 0, "C5 E9"), (3, 1, "94 29"), (3, 2, "64 29"), (3, 3, "35 E9"),
        # the manual's device-04 rows are shifted by one row; these are right
        (4, 0, "C4 5E"), (4, 1, "95 9E"), (4, 2, "65 9E"), (4, 3, "34 5E"),
    ],
)
def test_radar_sample_request_crcs(unit: int, address: int, crc: str) -> None:
    assert ReadRequest(unit, 3, address, 2).frame()[-2:] == frame(crc)


def test_radar_manual_row_for_device_4_address_1_is_wrong() -> None:
    # the manual prints 65 9E for 0x0001, which belongs to 0x0002
    assert ReadRequest(4, 3, 1, 2).frame()[-2:] != frame("65 9E")


def test_irnet_reset_coil_frame() -> None:
    assert WriteSingle(1, 5, 0x00D0, 0).frame() == frame("01 05 00 D0 00 00 CC 33")


def test_huiwen_address_write_request_matches_manual() -> None:
    assert WriteSingle(1, 6, 0x9C41, 1).frame() == frame("01 06 9C 41 00 01 36 4E")


def test_every_seed_profile_is_bundled_and_valid() -> None:
    lib = load_library()
    assert set(SEEDS) <= set(lib.profiles)
    for pid in SEEDS:
        p = lib.get(pid)
        assert p.fields, pid
        assert all(f.name == f.name.lower() for f in p.fields)


@pytest.mark.parametrize(
    ("pid", "names"),
    [
        ("net-irnet-pro", {"temperature", "concentration", "error", "warning",
                           "calibration_gas_level"}),
        ("radar-level", {"air_gap_cm", "air_gap_mm", "level_cm", "level_mm"}),
        ("huiwen-aq", {"pm25", "tvoc", "hcho", "co2", "temperature", "humidity", "pm25_level",
                       "co2_level", "pm25_failure", "th_failure"}),
        ("co2meter-an117", {"co2"}),
    ],
)
def test_stable_field_names(pid: str, names: set[str]) -> None:
    assert names <= set(load_one(pid).names())


def test_addressing_conventions() -> None:
    assert load_one("huiwen-aq").field("pm25").address == 0x7536  # 30006 sent as-is
    assert load_one("huiwen-aq").field("slave_address").address == 0x9C41
    assert load_one("banner-ez-array").field("measurement_1").address == 0x7531
    assert load_one("co2meter-an117").field("co2").address == 0x0001  # 1-based, sent as-is
    assert Addressing.MODICON.to_wire(Table.HOLDING, 40001) == 0
    assert Addressing.MODICON.to_wire(Table.INPUT, 30006) == 5
    assert Addressing.ONE_BASED.to_wire(Table.INPUT, 4) == 3


def test_device_quirks_are_in_the_profiles() -> None:
    co2 = load_one("co2meter-an117")
    assert co2.serial.deassert_dtr and co2.addresses.any == 0xFE
    assert 0xCC in co2.addresses.reserved and co2.limits.max_registers == 8
    assert co2.limits.silent_on_error and co2.field("co2").layout.type.value == "i16"
    banner = load_one("banner-ez-array")
    assert 6 not in banner.limits.functions and banner.set_address.function == 16
    assert {f.name for f in banner.forbidden()} == {"analog_1_peak", "analog_2_peak"}
    radar = load_one("radar-level")
    assert all(f.alone for f in radar.fields) and radar.limits.functions == {3, 6}
    irnet = load_one("net-irnet-pro")
    assert irnet.variant is not None and irnet.variant.on_exception == {2: 0}
    assert irnet.field("calibration_gas_level").since == 1
    assert irnet.field("uart_speed").since == 1
    assert irnet.set_address.field is None and "read-only" in irnet.set_address.unsupported
    assert load_one("huiwen-aq").set_address.reply == "any"


def test_enum_other_names_undocumented_codes() -> None:
    status = load_one("radar-level").field("status")
    assert interpret(status, (0,)).value == "OK"
    fv = interpret(status, (7,))
    assert fv.value == "MEASUREMENT_ERROR (7)" and fv.severity.value == "error"


def test_irnet_error_is_an_enum_and_warning_a_bitfield() -> None:
    p = load_one("net-irnet-pro")
    err = interpret(p.field("error"), (0x18,))
    assert err.value == "LAMP_ERROR" and err.severity.value == "error"
    warn = interpret(p.field("warning"), (0x11,))
    assert warn.value == ["WARMUP_WARNING", "INVALID_READINGS_WARNING"]
    assert warn.severity.value == "warning"
    assert interpret(p.field("error"), (0x30,)).value == "unknown (48)"


def test_field_words_is_the_inverse_of_interpret() -> None:
    p = load_one("net-irnet-pro")
    for name, value in [("warning", ["WARMUP_WARNING", "HW_TEST_WARNING"]),
                        ("error", "SPI_ERROR"), ("concentration", -20.0),
                        ("serial_number", "AB12")]:
        f = p.field(name)
        assert interpret(f, field_words(f, value)).value == value


def test_banner_never_fields_are_not_polled() -> None:
    banner = load_one("banner-ez-array")
    defaults = {f.name for f in banner.default_fields()}
    assert "analog_1_peak" not in defaults
    assert banner.field("analog_1_peak").poll is Poll.NEVER


def test_user_directory_shadows_bundled(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = Path(load_one("co2meter-an117").path).read_text()
    (tmp_path / "co2meter-an117.yaml").write_text(src.replace("model: Modbus sensor board",
                                                              "model: My board"))
    monkeypatch.setenv("RTUPOLL_PROFILES", str(tmp_path))
    assert load_one("co2meter-an117").model.startswith("My board")
    assert load_library().get("co2meter-an117").path == str(tmp_path / "co2meter-an117.yaml")


def test_the_documented_example_profile_loads(tmp_path: Path) -> None:
    doc = (Path(__file__).parents[2] / "docs" / "profiles.md").read_text()
    example = doc.split("```yaml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "acme-th100.yaml"
    path.write_text(example)
    from rtupoll.config.library import load_profile

    p = load_profile(path)
    assert p.field("temperature").address == 0  # modicon 30001 -> wire 0
    assert p.field("energy").layout.order.value == "CDAB"
    assert p.field("slave_address").layout.byte == "high"
    assert interpret(p.field("status"), (9,)).value == "FAULT (9)"
    assert p.addresses.check(0xCC) is not None and p.addresses.check(5) is None


SIX_DIGITS = """\
id: six
vendor: Test
model: Meter
manual: none
addressing: modicon
fields:
  - {name: voltage, table: input, address: 30001, type: f32}
  - {name: meter_code, table: holding, address: 464515, type: u16}
  - {name: far, table: holding, address: 49999, type: u16}
"""


@pytest.mark.parametrize(("written", "wire", "shown"), [
    (464515, 0xFC02, "464515"), (465536, 0xFFFF, "465536"), (400001, 0, "40001"),
    (49999, 9998, "49999"), (40001, 0, "40001")])
def test_modicon_profiles_take_the_6_digit_form_past_9999(written: int, wire: int,
                                                          shown: str) -> None:
    """Eastron writes 464515 for holding 0xFC02; one rule for profiles and raw reads,
    and an address is shown in the 5-digit form while it fits (400001 is 40001)."""
    from rtupoll.model.raw import modicon_wire

    assert Addressing.MODICON.to_wire(Table.HOLDING, written) == wire
    assert modicon_wire(Table.HOLDING, written) == wire
    assert Addressing.MODICON.show(Table.HOLDING, wire) == shown


def test_a_6_digit_modicon_field_loads_shows_and_a_5_digit_past_49999_is_refused(
        tmp_path: Path) -> None:
    from cli_runner import rtupoll

    from rtupoll.config.library import load_profile

    path = tmp_path / "six.yaml"
    path.write_text(SIX_DIGITS)
    p = load_profile(path)
    assert p.field("meter_code").address == 0xFC02 and p.field("far").address == 9998
    show = rtupoll("profiles", "show", str(path), env={"COLUMNS": "120"})
    assert "464515" in show.stdout and "0xFC02" in show.stdout
    path.write_text(SIX_DIGITS.replace("address: 49999", "address: 50001"))
    bad = rtupoll("profiles", "check", str(path))
    assert bad.returncode == 2
    assert ("fields[2].address: 50001 is not a holding register reference (40001..49999, "
            "or 400001..465536)") in bad.stderr
