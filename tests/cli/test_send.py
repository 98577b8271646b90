"""``rtupoll send``: one request of any function through the line discipline, its reply
decoded; golden frames from a vendor's manual and the Modbus specification, the rest
against the simulator."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.rtu import identification as ident
from rtupoll.rtu import with_crc
from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.functions import reply_length
from rtupoll.rtu.match import answers, expect_for
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
FIXTURES = Path(__file__).parents[1] / "fixtures" / "send"
# KBR multicomp F144 manual, "Device information", example Modbus RTU: request and reply
KBR_REQUEST = "01 2B 0E 01 00 70 77"
KBR_REPLY = ("01 2B 0E 01 01 00 00 03 00 08 4B 42 52 20 47 6D 62 48 01 12 6D 75 6C 74 69 63"
             " 6F 6D 70 20 46 31 34 34 2D 33 20 20 02 09 20 32 2E 30 30 72 30 31 36 CD DB")


def test_a_vendors_device_identification_example_is_framed_and_parsed() -> None:
    request, reply = bytes.fromhex(KBR_REQUEST), bytes.fromhex(KBR_REPLY)
    assert with_crc(b"\x01" + ident.device_id_request(1, 0)) == request
    assert crc_ok(reply) and reply_length(reply) == len(reply)  # its objects say its end
    assert reply_length(reply[:20]) is None  # not yet: the last object's length is to come
    assert answers(reply, expect_for(request))  # type: ignore[arg-type]
    got = ident.parse_device_id(reply[1:-2])
    assert (got.code, got.conformity, got.more) == (1, 0x01, False)
    assert dict(got.objects) == {0: b"KBR GmbH", 1: b"multicomp F144-3  ", 2: b" 2.00r016"}


def test_the_specifications_diagnostics_echo_through_the_line(sim: Sim) -> None:
    """Modbus Application Protocol V1.1b3, 6.8.1.1: sub-function 00 00, data A5 37, comes
    back as it was sent."""
    bus = sim("identified-meter@1", tick=None, profile_dirs=[FIXTURES])
    run = rtupoll("send", "-p", bus.port, "-b", "2400", "diagnostics", "1", "0", "A537")
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines()[:2] == [
        "request  01 08 00 00 A5 37 DA 8D   diagnostics: return query data",
        "reply    01 08 00 00 A5 37 DA 8D"]
    assert "A5 37  (the request's, echoed)" in run.stdout


def test_device_identification_in_every_part_of_a_split_reply(sim: Sim) -> None:
    bus = sim("identified-meter@1", tick=None, profile_dirs=[FIXTURES])
    run = rtupoll("send", "-p", bus.port, "-b", "2400", "--format", "json",
                  "read-device-id", "1", "extended")
    assert run.returncode == 0, run.stderr
    rec = json.loads(run.stdout)
    assert len(rec["replies"]) == 2  # "more follows", and the second part asked for
    assert rec["objects"]["VendorName"] == "KBR GmbH"
    assert rec["objects"]["MajorMinorRevision"] == " 2.00r016"
    assert rec["objects"]["private 0x81"].startswith("the second private object")
    assert rec["complete"] is True
    basic = rtupoll("send", "-p", bus.port, "-b", "2400", "read-device-id", "1")
    assert basic.returncode == 0, basic.stderr
    assert "  ProductCode          multicomp F144-3" in basic.stdout


def test_report_server_id_and_an_exception_by_name(sim: Sim) -> None:
    bus = sim("identified-meter@1", "radar-level@2", tick=None, profile_dirs=[FIXTURES])
    run = rtupoll("send", "-p", bus.port, "-b", "2400", "report-server-id", "1")
    assert run.returncode == 0, run.stderr
    assert "  server id            0A" in run.stdout and "run indicator        ON" in run.stdout
    missing = rtupoll("send", "-p", bus.port, "-b", "2400", "read-device-id", "1", "7")
    assert missing.returncode == 5
    assert "  exception 02 ILLEGAL DATA ADDRESS" in missing.stdout
    unsupported = rtupoll("send", "-p", bus.port, "-b", "2400", "report-server-id", "2")
    assert unsupported.returncode == 5 and "exception 01 ILLEGAL FUNCTION" in unsupported.stdout


def test_a_raw_pdu_reads_through_the_line(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None, sets=["huiwen-aq@3.co2=800"])
    run = rtupoll("send", "-p", bus.port, "3", "04", "75 39", "00 01")  # 30010: co2
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines()[1].startswith("reply    03 04 02 03 20 ")  # 800


@pytest.mark.parametrize(("request_", "why"), [
    (["3", "06", "9C41", "0005"], "write single register is a write"),
    (["diagnostics", "3", "4"], "diagnostics: force listen only mode is a state-changing"),
    (["3", "41", "00"], "of unknown effect"),
])
def test_what_changes_a_device_needs_yes(sim: Sim, request_: list[str], why: str) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    run = rtupoll("send", "-p", bus.port, *request_)
    assert run.returncode == 8, run
    assert "add --yes" in run.stderr
    assert bus.engine.requests == 0  # nothing was sent


def test_a_write_with_yes_is_sent_and_echoed(sim: Sim) -> None:
    bus = sim("radar-level@2", tick=None)
    run = rtupoll("send", "-p", bus.port, "--yes", "2", "06", "03F4", "0002")  # its address
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines()[1].startswith("reply    02 06 03 F4 00 02")


@pytest.mark.parametrize(("args", "message"), [
    (["0", "04", "0000", "0001"], "unit 0 is a broadcast"),
    (["3", "zz"], "is not bytes in hex"),
    (["read-device-id"], "read-device-id needs UNIT"),
    (["3"], "give the request PDU in hex"),
    (["diagnostics", "3", "10000"], "outside 0..0xFFFF"),
])
def test_bad_requests_are_one_line(args: list[str], message: str) -> None:
    run = rtupoll("send", "-p", "/dev/null", *args)
    assert run.returncode == 2
    assert message in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr
