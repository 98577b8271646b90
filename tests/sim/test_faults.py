"""Every fault kind, shown by the bytes a raw client gets from the pty.

Each test pins a value so the healthy reply is known exactly, then checks the fault
turned it into what the fault says -- and that the wire log records the same bytes.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
from conftest import RawPort

from rtupoll import rtu
from rtupoll.errors import FaultSpecError
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
Raw = Callable[[str], RawPort]

READ = ReadRequest(1, 4, 0x0006, 2).frame()  # IRNET concentration
GOOD = bytes.fromhex("01 04 04 00 00 A0 C1 42 14")  # -20.0
PIN = ["net-irnet-pro@1.concentration=-20"]


def irnet(sim: Sim, *faults: str, **kw: object) -> SimulatedBus:
    return sim("net-irnet-pro@1", "huiwen-aq@3", faults=faults, sets=PIN, tick=None, **kw)


def test_no_fault_is_the_golden_reply(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim)
    assert raw_port(bus.port).transact(READ, len(GOOD)) == GOOD


def test_dead_device_never_answers_and_the_others_still_do(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:dead")
    port = raw_port(bus.port)
    assert port.transact(READ, timeout=0.2) == b""
    assert port.transact(ReadRequest(3, 3, 40001, 1).frame(), 7) == \
        ReadReply(3, 3, (3,)).frame()
    assert [w.data for w in bus.wire if w.direction == "out"] == [ReadReply(3, 3, (3,)).frame()]


def test_slow_reply_misses_the_timeout_then_arrives_late(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:slow=0.3")
    port = raw_port(bus.port)
    sent = port.send(READ)
    assert port.read(timeout=0.15) == b""  # a client with a 150 ms timeout gives up
    late = port.read(len(GOOD))
    assert late == GOOD  # ... and the reply still comes, late, for the next read to find
    out = [w for w in bus.wire if w.direction == "out"]
    assert out[0].data == GOOD and out[0].time - sent >= 0.29 and "slow 0.3s" in out[0].note


def test_crc_error_keeps_the_body_and_breaks_the_crc(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:crc")
    got = raw_port(bus.port).transact(READ, len(GOOD))
    assert got[:-2] == GOOD[:-2] and got[-2:] == bytes([GOOD[-2] ^ 0xFF, GOOD[-1] ^ 0xFF])
    assert not rtu.crc_ok(got)


@pytest.mark.parametrize(("spec", "byte"), [("stray", 0x00), ("stray=0xFF", 0xFF)])
def test_stray_byte_before_the_reply(sim: Sim, raw_port: Raw, spec: str, byte: int) -> None:
    bus = irnet(sim, spec)  # bus-wide: every device's replies
    assert raw_port(bus.port).transact(READ, len(GOOD) + 1) == bytes([byte]) + GOOD


def test_truncated_reply(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:truncate=5")
    port = raw_port(bus.port)
    assert port.transact(READ, 5) == GOOD[:5]
    assert port.read(timeout=0.1) == b""  # and no more
    bus2 = irnet(sim, "1:truncate")  # default: half the frame
    port2 = raw_port(bus2.port)
    assert port2.transact(READ, 4) == GOOD[:4]
    assert port2.read(timeout=0.1) == b""


def test_reply_from_the_wrong_id_alone(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:wrong-id=2")
    assert raw_port(bus.port).transact(READ, len(GOOD)) == rtu.with_crc(b"\x02" + GOOD[1:-2])


def test_reply_from_the_wrong_id_together_with_the_right_one(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:wrong-id-first")  # default id: the next address
    wrong = rtu.with_crc(b"\x02" + GOOD[1:-2])
    assert raw_port(bus.port).transact(READ, 2 * len(GOOD)) == wrong + GOOD
    assert bus.wire[-1].data == wrong + GOOD  # one write: they arrive together


@pytest.mark.parametrize(("spec", "code"), [("1:exception", 4), ("1:exception=6", 6)])
def test_exception_reply(sim: Sim, raw_port: Raw, spec: str, code: int) -> None:
    bus = irnet(sim, spec)
    assert raw_port(bus.port).transact(READ, 5) == ExceptionReply(1, 4, code).frame()


def test_lose_first_requests_after_power_up(sim: Sim, raw_port: Raw) -> None:
    bus = sim("co2meter-an117@4", "huiwen-aq@3", faults=["lose-first"],
              sets=["co2meter-an117@4.co2=400"], tick=None)
    port = raw_port(bus.port)
    co2 = ReadRequest(4, 4, 1, 1).frame()
    # the profile's limits.lost_after_powerup is 3; huiwen-aq has none, so it loses 3
    assert [port.transact(co2, timeout=0.1) for _ in range(3)] == [b""] * 3
    assert port.transact(co2, 7) == ReadReply(4, 4, (400,)).frame()
    assert port.transact(co2, 7) == ReadReply(4, 4, (400,)).frame()


def test_lose_first_n_for_one_device(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:lose-first=1")
    port = raw_port(bus.port)
    assert port.transact(READ, timeout=0.1) == b""
    assert port.transact(READ, len(GOOD)) == GOOD


def test_schedule_hits_exactly_the_named_requests(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim, "1:crc@2,4-5")
    port = raw_port(bus.port)
    ok = [rtu.crc_ok(port.transact(READ, len(GOOD))) for _ in range(6)]
    assert ok == [True, False, True, False, False, True]


def test_rates_are_repeatable_with_a_seed(sim: Sim, raw_port: Raw) -> None:
    def run(seed: int) -> list[bool]:
        bus = irnet(sim, "1:crc@30%", seed=seed)
        port = raw_port(bus.port)
        return [rtu.crc_ok(port.transact(READ, len(GOOD))) for _ in range(30)]

    first = run(11)
    assert first == run(11)
    assert 3 <= first.count(False) <= 18  # about 30 % of 30


def test_garbage_before_a_request_is_skipped_byte_by_byte(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim)
    port = raw_port(bus.port)
    assert port.transact(b"\x00\xff\x01\x04" + READ, len(GOOD)) == GOOD
    assert [w.note for w in bus.wire[:2]] == ["garbage", "unit 1 read input registers 0x0006 x2"]
    # a half frame, a pause, then a whole one
    port.send(READ[:5])
    time.sleep(0.02)
    assert port.transact(READ, len(GOOD)) == GOOD


def test_unknown_function_gets_exception_01(sim: Sim, raw_port: Raw) -> None:
    bus = irnet(sim)
    report_id = rtu.with_crc(b"\x01\x11")  # FC17 report server id
    assert raw_port(bus.port).transact(report_id, 5) == ExceptionReply(1, 0x11, 1).frame()


# -- the spec syntax --------------------------------------------------------------

def test_fault_spec_parts() -> None:
    f = parse_fault("0xFE:slow=1.5@2,5-7,10-")
    assert (f.target, f.kind, f.arg, f.rate) == (254, "slow", 1.5, None)
    assert [f.scheduled(n) for n in (1, 2, 5, 7, 8, 10, 99)] == \
        [False, True, True, True, False, True, True]
    assert parse_fault("crc@10%").rate == pytest.approx(0.1)
    assert parse_fault("crc@0.25").rate == 0.25
    assert parse_fault("stray=0xFF").arg == 255


@pytest.mark.parametrize(("spec", "message"), [
    ("3:deadd", "did you mean 'dead'"),
    ("crc=3", "crc takes no argument"),
    ("slow=abc", "not seconds"),
    ("exception=0", "outside 1..255"),
    ("crc@150%", "outside 0..1"),
    ("crc@0", "requests count from 1"),
    ("lose-first@3", "give N as lose-first=N"),
    ("x:crc", "address 'x' is not a whole number"),
])
def test_bad_fault_specs_say_why(spec: str, message: str) -> None:
    with pytest.raises(FaultSpecError, match=message):
        parse_fault(spec)


def test_fault_for_a_missing_device_is_refused(sim: Sim) -> None:
    with pytest.raises(Exception, match="no device at 9"):
        sim("net-irnet-pro@1", faults=["9:dead"])
