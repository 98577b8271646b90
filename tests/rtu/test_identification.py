"""Read device identification and report server id, built and parsed (sans-IO)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.profile_file import read_profile
from rtupoll.errors import ProfileError
from rtupoll.rtu import identification as ident

OBJECTS = {0: b"Vendor", 1: b"P1", 2: b"V1", 0x80: b"x" * 200, 0x81: b"y" * 200}


def test_a_reply_too_long_for_one_frame_says_more_follows_and_where_to_go_on() -> None:
    first = ident.parse_device_id(ident.device_id_reply(3, 0, OBJECTS))
    assert first.more and first.next_object == 0x81
    assert [o for o, _ in first.objects] == [0, 1, 2, 0x80]
    rest = ident.parse_device_id(ident.device_id_reply(3, first.next_object, OBJECTS))
    assert not rest.more and dict(rest.objects) == {0x81: b"y" * 200}


def test_codes_choose_the_objects_and_a_missing_start_starts_over() -> None:
    basic = ident.parse_device_id(ident.device_id_reply(1, 0, OBJECTS))
    assert [o for o, _ in basic.objects] == [0, 1, 2]
    again = ident.parse_device_id(ident.device_id_reply(1, 5, OBJECTS))  # no object 5
    assert [o for o, _ in again.objects] == [0, 1, 2]
    one = ident.parse_device_id(ident.device_id_reply(4, 0x80, OBJECTS))
    assert dict(one.objects) == {0x80: b"x" * 200}
    with pytest.raises(ValueError, match="no object 0x05"):
        ident.device_id_reply(4, 5, OBJECTS)


@pytest.mark.parametrize(("pdu", "why"), [
    (bytes.fromhex("2B0E0101000001"), "1 objects announced"),
    (bytes.fromhex("2B0E01010000010005414243"), "announces 5 bytes, 3 follow"),
    (bytes.fromhex("2B0E010100000100014142"), r"1 byte\(s\) after the last object"),
    (bytes.fromhex("2B0E01017F0000"), "'more follows' is 0x7F"),
    (bytes.fromhex("2B0D01010000"), "not a read device identification reply"),
])
def test_replies_that_do_not_add_up_say_why(pdu: bytes, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        ident.parse_device_id(pdu)


def test_report_server_id_finds_the_run_indicator_where_the_standard_puts_it() -> None:
    sid = ident.parse_server_id(ident.server_id_reply(b"\x0a", True, b"AB"))
    assert (sid.server_id, sid.running, sid.additional) == (b"\x0a", True, b"AB")
    longer = ident.parse_server_id(bytes.fromhex("1103414243"))  # a 3-byte id, no indicator
    assert longer.running is None and longer.additional == b"BC"
    with pytest.raises(ValueError):
        ident.parse_server_id(bytes.fromhex("110541"))


@pytest.mark.parametrize(("text", "why"), [
    ("identification: {vendor_name: A, product_code: B}", "missing 'major_minor_revision'"),
    ("identification: {vendor: A}", "not an identification object: 'vendor'"),
    ("identification: {0x10: A}", "not an identification object: '0x10'"),
    ("server_id: zz", "expected bytes in hex"),
])
def test_profile_identification_mistakes_name_file_and_line(tmp_path: Path, text: str,
                                                            why: str) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text(f"id: mine\nextends: radar-level\n{text}\n", encoding="utf-8")
    with pytest.raises(ProfileError) as info:
        read_profile(path)
    assert str(info.value).startswith(f"{path}:3: ") and why in str(info.value)
