"""Simulated devices, byte for byte: the manuals' golden frames and each profile's quirks.

These drive the RTU engine directly (no pty), so each test reads as "this request gets
exactly this reply (or silence)".
"""

from __future__ import annotations

import pytest

from rtupoll import rtu
from rtupoll.errors import RefusedError, UsageError
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest, WriteMultiple, WriteSingle
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build


def make(*devices: str, **kw: object) -> Engine:
    config = build(devices, **kw)  # type: ignore[arg-type]
    return Engine(config.devices, config.faults, seed=config.seed, tick=None)


def ask(engine: Engine, frame: bytes | str) -> bytes:
    """What goes back on the wire for one request (b"" is silence)."""
    data = bytes.fromhex(frame) if isinstance(frame, str) else frame
    return b"".join(t.data for t in engine.handle(data))


def exc(unit: int, fc: int, code: int) -> bytes:
    return ExceptionReply(unit, fc, code).frame()


# -- golden frames from the manuals (design.md) -----------------------------------

def test_irnet_concentration_golden_frame() -> None:
    e = make("net-irnet-pro@1", sets=["net-irnet-pro@1.concentration=-20"])
    assert ask(e, "01 04 00 06 00 02 91 CA") == bytes.fromhex("01 04 04 00 00 A0 C1 42 14")


def test_irnet_calibration_gas_golden_frame() -> None:
    e = make("net-irnet-pro@1", sets=["net-irnet-pro@1.calibration_gas_level=50"])
    assert ask(e, "01 03 02 00 00 02 C5 B3") == bytes.fromhex("01 03 04 00 00 48 42 4C 02")


def test_irnet_reset_coil_is_echoed() -> None:
    assert ask(make("net-irnet-pro@1"), "01 05 00 D0 00 00 CC 33") == \
        bytes.fromhex("01 05 00 D0 00 00 CC 33")


def test_huiwen_block_read_bridges_the_undocumented_register() -> None:
    e = make("huiwen-aq@1", sets=["huiwen-aq@1.pm25=25", "huiwen-aq@1.tvoc=0.05",
                                  "huiwen-aq@1.hcho=0.25", "huiwen-aq@1.co2=5000"])
    assert ask(e, "01 04 75 36 00 05 CA 0B") == \
        bytes.fromhex("01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94")


def test_huiwen_slave_address_golden_frame() -> None:
    assert ask(make("huiwen-aq@1"), "01 03 9C 41 00 01 FA 4E") == \
        bytes.fromhex("01 03 02 00 01 79 84")


def test_co2meter_any_sensor_address_golden_frame() -> None:
    e = make("co2meter-an117@4", sets=["co2meter-an117@4.co2=400"])
    assert ask(e, "FE 04 00 01 00 01 74 05") == bytes.fromhex("FE 04 02 01 90 AC D8")
    assert ask(e, ReadRequest(4, 4, 1, 1).frame()) == ReadReply(4, 4, (400,)).frame()


def test_banner_example_a1_golden_frame() -> None:
    e = make("banner-ez-array@65", sets=["banner-ez-array@65.holding_40001=555",
                                         "banner-ez-array@65.holding_40002=0",
                                         "banner-ez-array@65.holding_40003=100"])
    assert ask(e, "41 03 9C 41 00 03 75 4F") == \
        bytes.fromhex("41 03 06 02 2B 00 00 00 64 34 B9")


def test_radar_golden_request_is_answered_per_register() -> None:
    e = make("radar-level@1", sets=["radar-level@1.air_gap_cm=123"])
    assert ask(e, "01 03 00 00 00 01 84 0A") == ReadReply(1, 3, (123,)).frame()
    # the profile reads 2 registers at most: a 2-register block works, 3 is refused
    assert ask(e, "01 03 00 00 00 02 C4 0B")[:3] == bytes.fromhex("01 03 04")
    assert ask(e, ReadRequest(1, 3, 0, 3).frame()) == exc(1, 3, 3)


# -- the map and the limits ------------------------------------------------------

def test_absent_unit_gets_silence_not_exception_04() -> None:
    assert ask(make("net-irnet-pro@1"), ReadRequest(9, 4, 6, 2).frame()) == b""


def test_outside_the_map_is_exception_02() -> None:
    e = make("net-irnet-pro@1", "banner-ez-array@5")
    assert ask(e, ReadRequest(1, 4, 0x0010, 1).frame()) == exc(1, 4, 2)
    # 0x0004..0x000F is mapped end to end; one register more is not
    assert ask(e, ReadRequest(1, 4, 4, 12).frame())[:3] == bytes.fromhex("01 04 18")
    assert ask(e, ReadRequest(1, 4, 4, 13).frame()) == exc(1, 4, 2)
    # Banner: 30002 -> 30026 is a gap of 23 > max_gap 8; 30028 -> 30030 may be bridged
    assert ask(e, ReadRequest(5, 4, 30002, 2).frame()) == exc(5, 4, 2)
    assert ask(e, ReadRequest(5, 4, 30028, 3).frame())[:3] == bytes.fromhex("05 04 06")


def test_unsupported_function_is_exception_01() -> None:
    e = make("radar-level@2", "banner-ez-array@5")
    assert ask(e, ReadRequest(2, 4, 0, 1).frame()) == exc(2, 4, 1)
    assert ask(e, WriteSingle(5, 6, 41000, 7).frame()) == exc(5, 6, 1)


def test_co2meter_is_silent_for_unsupported_and_malformed_but_not_for_unmapped() -> None:
    e = make("co2meter-an117@4")
    assert ask(e, ReadRequest(4, 1, 0, 1).frame()) == b""  # FC01: not supported
    assert ask(e, ReadRequest(4, 4, 1, 9).frame()) == b""  # over 8 registers
    assert ask(e, ReadRequest(4, 4, 2, 1).frame()) == exc(4, 4, 2)  # AN117: 02


def test_read_limit_is_exception_03() -> None:
    e = make("huiwen-aq@3")
    assert ask(e, ReadRequest(3, 4, 30006, 126).frame()) == exc(3, 4, 3)
    assert ask(e, ReadRequest(3, 4, 30006, 0).frame()) == exc(3, 4, 3)


def test_irnet_data_structure_1_by_default_and_0_as_an_option() -> None:
    e = make("net-irnet-pro@1")
    assert ask(e, ReadRequest(1, 4, 0x0400, 1).frame()) == ReadReply(1, 4, (1,)).frame()
    assert ask(e, ReadRequest(1, 3, 0x007C, 1).frame())[:3] == bytes.fromhex("01 03 02")
    e0 = make("net-irnet-pro@1", options=["net-irnet-pro@1.variant=0"])
    assert ask(e0, ReadRequest(1, 4, 0x0400, 1).frame()) == exc(1, 4, 2)
    assert ask(e0, ReadRequest(1, 3, 0x007C, 1).frame()) == exc(1, 3, 2)
    assert ask(e0, ReadRequest(1, 3, 0x0200, 2).frame()) == exc(1, 3, 2)


def test_reading_a_poll_never_register_resets_it() -> None:
    e = make("banner-ez-array@5", sets=["banner-ez-array@5.analog_2_dac=300"])
    peak = ReadRequest(5, 4, 30521, 1).frame()
    first = ask(e, peak)
    assert first[:3] == bytes.fromhex("05 04 02") and first[3:5] != b"\x00\x00"
    assert ask(e, peak) == ReadReply(5, 4, (0,)).frame()  # the read reset it
    e.devices[0].advance(3)
    assert ask(e, peak) != ReadReply(5, 4, (0,)).frame()  # and it rises again


# -- writes ----------------------------------------------------------------------

def test_write_to_read_only_register_is_exception_02() -> None:
    e = make("net-irnet-pro@1")
    assert ask(e, WriteMultiple(1, 16, 0x0016, (5,)).frame()) == exc(1, 16, 2)


def test_write_out_of_range_is_exception_03_and_changes_nothing() -> None:
    e = make("huiwen-aq@3")
    assert ask(e, WriteSingle(3, 6, 40001, 0).frame()) == exc(3, 6, 3)
    assert ask(e, WriteSingle(3, 6, 40001, 300).frame()) == exc(3, 6, 3)
    assert e.devices[0].address == 3


def test_huiwen_address_change_moves_the_device_with_an_echo() -> None:
    e = make("huiwen-aq@1")
    write = WriteSingle(1, 6, 40001, 7).frame()
    assert ask(e, write) == write
    assert ask(e, ReadRequest(1, 3, 40001, 1).frame()) == b""
    assert ask(e, ReadRequest(7, 3, 40001, 1).frame()) == ReadReply(7, 3, (7,)).frame()


@pytest.mark.parametrize(("reply", "expected"), [
    ("short", "01 06 02 00 01 79 48"),  # the Huiwen manual's own (non-echo) frame
    ("none", ""),
])
def test_huiwen_fc06_reply_options(reply: str, expected: str) -> None:
    e = make("huiwen-aq@1", options=[f"huiwen-aq@1.write_reply={reply}"])
    assert ask(e, "01 06 9C 41 00 01 36 4E") == bytes.fromhex(expected)


def test_banner_address_change_is_fc16_read_modify_write_of_the_low_byte() -> None:
    e = make("banner-ez-array@5")
    before = ask(e, ReadRequest(5, 3, 41000, 1).frame())
    word = int.from_bytes(before[3:5], "big")
    assert word & 0xFF == 5 and word >> 8 != 0  # the high byte holds something to keep
    new = (word & 0xFF00) | 9
    assert ask(e, WriteMultiple(5, 16, 41000, (new,)).frame()) == \
        rtu.with_crc(bytes.fromhex("05 10 A0 28 00 01"))
    assert ask(e, ReadRequest(5, 3, 41000, 1).frame()) == b""
    assert ask(e, ReadRequest(9, 3, 41000, 1).frame()) == ReadReply(9, 3, (new,)).frame()


def test_radar_address_change_by_fc06() -> None:
    e = make("radar-level@1", "co2meter-an117@4")
    assert ask(e, WriteSingle(1, 6, 0x03F4, 12).frame()) == WriteSingle(1, 6, 0x03F4, 12).frame()
    assert e.devices[0].address == 12
    assert ask(e, ReadRequest(12, 3, 0x03F4, 1).frame()) == ReadReply(12, 3, (12,)).frame()


def test_broadcast_write_is_applied_without_a_reply() -> None:
    e = make("huiwen-aq@3")
    assert ask(e, WriteSingle(0, 6, 40001, 9).frame()) == b""
    assert e.devices[0].address == 9


# -- pins ------------------------------------------------------------------------

def test_pins_go_through_the_codec_and_are_refused_when_they_do_not_fit() -> None:
    e = make("net-irnet-pro@1", sets=["net-irnet-pro@1.warning=WARMUP_WARNING,HW_TEST_WARNING",
                                      "net-irnet-pro@1.error=LAMP_ERROR"])
    d = e.devices[0]
    assert d.value("warning").value == ["WARMUP_WARNING", "HW_TEST_WARNING"]
    assert d.words(Table.INPUT, 8, 2) == (0x18, 0x81)
    with pytest.raises(RefusedError):
        d.pin("error", 70000)
    with pytest.raises(UsageError, match="no field 'nope'"):
        d.pin("nope", 1)
