"""``rtupoll decode`` against the seed manuals' own example frames, the wrong ones included."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.model.carried import carried
from rtupoll.rtu.capture import decode_stream, parse_hex, split


def frames(text: str, **kw: int):  # type: ignore[no-untyped-def]
    return decode_stream(parse_hex([text]), **kw)


def run(*args: str, input: str | None = None) -> tuple[int, str]:
    result = rtupoll(*args, input=input)
    return result.returncode, (result.stdout + result.stderr)


# --- frames that are right --------------------------------------------------------------

GOLDEN = [  # (profile, request, reply, field, value) from design.md's golden frames
    ("net-irnet-pro", "01 04 00 06 00 02 91 CA", "01 04 04 00 00 A0 C1 42 14",
     "concentration", -20.0),
    ("net-irnet-pro", "01 03 02 00 00 02 C5 B3", "01 03 04 00 00 48 42 4C 02",
     "calibration_gas_level", 50.0),
    ("huiwen-aq", "01 04 75 36 00 05 CA 0B", "01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94",
     "co2", 5000),
    ("huiwen-aq", "01 03 9C 41 00 01 FA 4E", "01 03 02 00 01 79 84", "slave_address", 1),
    ("co2meter-an117", "FE 04 00 01 00 01 74 05", "FE 04 02 01 90 AC D8", "co2", 400),
    ("banner-ez-array", "41 03 9C 41 00 03 75 4F", "41 03 06 02 2B 00 00 00 64 34 B9",
     "holding_40001", 555),
]


@pytest.mark.parametrize(("pid", "req_hex", "reply_hex", "name", "value"), GOLDEN)
def test_a_captured_exchange_splits_into_request_and_reply_with_the_fields(
        pid: str, req_hex: str, reply_hex: str, name: str, value: object) -> None:
    req, rep = frames(f"{req_hex} {reply_hex}")
    assert (req.kind, rep.kind) == ("request", "response")
    assert req.crc_ok and rep.crc_ok
    assert rep.start == req.start and rep.count == req.count  # the reply learns its addresses
    got = {c.name: c.value for c in carried(rep, load_one(pid))}
    assert got[name] == value


def test_the_radar_request_of_device_01_is_a_two_register_read() -> None:
    (f,) = frames("01 03 00 00 00 02 C4 0B")
    assert (f.kind, f.unit, f.function, f.start, f.count, f.crc_ok) == \
        ("request", 1, 3, 0, 2, True)


def test_a_write_and_its_echo_are_request_then_confirmed_reply() -> None:
    req, rep = frames("01 05 00 D0 00 00 CC 33 01 05 00 D0 00 00 CC 33")  # IRNET reset coil
    assert (req.kind, rep.kind) == ("request", "response")
    assert "echo of the request" in " ".join(rep.notes)


# --- frames the manuals got wrong --------------------------------------------------------

def test_irnet_error_example_has_the_wrong_function_and_a_zero_crc() -> None:
    _, err = frames("01 04 00 06 00 02 91 CA 01 90 01 00 00")
    assert err.kind == "exception" and err.exception == 1
    assert not err.crc_ok and err.crc_expected == bytes.fromhex("8D C0")
    notes = " ".join(err.notes)
    assert "0x84" in notes and "01 84 01 82 C0" in notes  # what the reply to FC04 looks like


def test_radar_device_04_rows_carry_the_crc_of_the_next_row() -> None:
    (f,) = frames("04 03 00 01 00 02 65 9E")
    assert not f.crc_ok and f.crc_expected == bytes.fromhex("95 9E")
    assert any("address 0x0002" in n for n in f.notes)


def test_huiwen_fc06_reply_is_not_an_echo_and_says_to_read_back() -> None:
    _, reply = frames("01 06 9C 41 00 01 36 4E 01 06 02 00 01 79 48")
    assert reply.crc_ok and reply.kind == "response"
    assert any("not an echo" in n and "read the register back" in n for n in reply.notes)


def test_huiwen_level_example_with_byte_count_06_over_eight_data_bytes() -> None:
    _, reply = frames("01 04 75 54 00 04 AA 15 01 04 06 00 01 00 01 00 02 00 00 E4 AD")
    assert reply.crc_ok and reply.values == (1, 1, 2, 0)
    assert any("byte count says 6, 8 data bytes follow" in n for n in reply.notes)


def test_swapped_crc_bytes_are_recognised() -> None:
    (f,) = frames("01 04 00 06 00 02 CA 91")
    assert any("swapped" in n for n in f.notes)


# --- streams -----------------------------------------------------------------------------

def test_stray_bytes_between_frames_are_noise_and_do_not_break_pairing() -> None:
    fs = frames("00 01 04 00 06 00 02 91 CA FF 01 04 04 00 00 A0 C1 42 14")
    assert [f.kind for f in fs] == ["noise", "request", "noise", "response"]
    assert fs[3].start == 6


def test_a_lone_reply_gets_its_address_from_start() -> None:
    (f,) = frames("01 03 02 00 01 79 84", start=0x9C41)
    assert f.start == 0x9C41
    assert carried(f, load_one("huiwen-aq"))[0].value == 1


def test_split_offsets_cover_the_stream() -> None:
    data = bytes.fromhex("01 04 00 06 00 02 91 CA 01 04 04 00 00 A0 C1 42 14")
    parts = split(data)
    assert b"".join(p[1] for p in parts) == data and [p[0] for p in parts] == [0, 8]


@pytest.mark.parametrize("text", ["0x01,0x04", "01:04", "0104", "1 4"])
def test_hex_is_accepted_in_the_usual_spellings(text: str) -> None:
    assert parse_hex([text]) == [b"\x01\x04"]


# --- the command --------------------------------------------------------------------------

def test_cli_text_shows_fields_and_the_manuals_addresses() -> None:
    code, out = run("decode", "--profile", "huiwen-aq", "01 04 75 36 00 05 CA 0B",
                    "01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94")
    assert code == 0
    assert "co2 (30009) = 5000 ppm" in out and "tvoc (30007) = 0.050 ppm" in out


def test_cli_bad_crc_exits_7_and_prints_the_expected_crc() -> None:
    code, out = run("decode", "01", "90", "01", "00", "00")
    assert code == 7
    assert "BAD (expected 8D C0)" in out


def test_cli_json_reads_lines_from_stdin_one_frame_per_line() -> None:
    code, out = run("decode", "--format", "json", "-",
                    input="04 03 00 00 00 02 C4 5E\n04 03 00 01 00 02 95 9E\n")
    records = [json.loads(line) for line in out.splitlines()]
    assert code == 0 and [r["start"] for r in records] == [0, 1]
    assert all(r["crc_ok"] for r in records)


def test_cli_rejects_text_that_is_not_hex() -> None:
    code, out = run("decode", "01 0G")
    assert code == 2 and "not hex" in out


def test_decode_json_path_imports_neither_pymodbus_nor_rich() -> None:
    code = ("import sys; from rtupoll.cli import main\n"
            "try:\n main(['decode','--format','json','--profile','net-irnet-pro',"
            "'01 04 00 06 00 02 91 CA 01 04 04 00 00 A0 C1 42 14'])\n"
            "except SystemExit: pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pymodbus','rich')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
