"""The Modbus RTU CRC-16 (rtupoll/rtu/crc.py)."""

from __future__ import annotations

from rtupoll.rtu import crc


def test_the_written_out_table_is_the_polynomials() -> None:
    assert crc.crc_table() == crc._CRC_TABLE
    assert len(crc._CRC_TABLE) == 256


def test_a_known_frame_checks() -> None:
    # read holding register 0, one register, from unit 1: the CRC every manual shows
    frame = crc.with_crc(bytes.fromhex("010300000001"))
    assert frame.hex() == "010300000001840a"
    assert crc.crc_ok(frame) and not crc.crc_ok(frame[:-1] + b"\x0b")
    assert crc.crc16(b"") == 0xFFFF
