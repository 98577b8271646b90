"""One master transaction (rtupoll.rtu.transaction), sans-IO, in virtual time: the
driver's side is played by hand (send at the time asked, feed bytes, expire)."""

from __future__ import annotations

import pytest

from rtupoll.rtu import Framing, Table
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.functions import MAX_QUANTITY
from rtupoll.rtu.line import Line
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest, WriteSingle
from rtupoll.rtu.transaction import (
    Await,
    BusStats,
    Done,
    Failed,
    Refused,
    Send,
    Transaction,
    pdu_frame,
    read_request,
    write_coil_request,
    write_registers_request,
)

FRAMING = Framing(9600)
REQ = ReadRequest(3, 4, 10, 2).frame()
GOOD = ReadReply(3, 4, (7, 8)).frame()


def fresh() -> Line:
    line = Line(FRAMING)
    line.opened(0.0)  # the port opened at t = 0
    return line


def send(tx: Transaction, now: float = 0.0) -> float:
    """Send as the driver does: at the time asked, or now if that has passed."""
    step = tx.next()
    assert isinstance(step, Send) and step.frame == tx.request
    at = max(step.at, now)
    tx.sent(at)
    return at


def test_an_answer_is_done_with_its_reply_time_and_counted() -> None:
    line, stats = fresh(), BusStats()
    tx = Transaction(line, REQ, timeout=0.5)
    at = send(tx)
    assert tx.next() == Await(at + tx.limit)
    assert tx.limit == pytest.approx(0.5 + FRAMING.wire_time(len(REQ) + len(GOOD)))
    assert tx.received(GOOD, at + 0.05)
    done = tx.next()
    assert isinstance(done, Done) and done.frame == GOOD and done.outcome == "ok"
    assert done.reply_time == pytest.approx(0.05 - FRAMING.wire_time(len(REQ)))
    stats.add(tx, 0.06)
    assert (stats.transactions, stats.attempts, stats.retries) == (1, 1, 0)
    assert stats.outcomes["ok"] == 1
    assert stats.wire == pytest.approx(FRAMING.wire_time(len(REQ) + len(GOOD)))
    ev = tx.evidence()
    assert (ev.reply_time, ev.late, ev.attempts) == (done.reply_time, 0, 1)


def test_timeouts_are_retried_after_the_silence_and_the_last_failure_says_tries() -> None:
    line = fresh()
    tx = Transaction(line, REQ, timeout=0.2, retries=2)
    first = send(tx)
    tx.expired(first + tx.limit)
    retry = tx.next()
    # a retry honours only the silence (long over), not the drain: it goes at once
    assert isinstance(retry, Send) and retry.at < first + tx.limit
    second = send(tx, first + tx.limit)
    tx.expired(second + tx.limit)
    send(tx, second + tx.limit)
    tx.expired(tx.deadline)
    failed = tx.next()
    assert isinstance(failed, Failed) and failed.kind == "timeout"
    assert failed.why == "no reply from unit 3 to read input registers within 0.2 s (3 tries)"
    assert tx.outcome == "timeout" and tx.attempts == 3
    # the next transaction waits for the drain: the line was quiet for the timeout
    later = Transaction(line, ReadRequest(4, 4, 0, 1).frame(), timeout=0.2)
    assert later.ready_at() >= tx.deadline + 0.2


def test_a_garbled_reply_is_retried_at_once_and_the_retry_answers() -> None:
    line = fresh()
    tx = Transaction(line, REQ, timeout=2.0, retries=1)
    at = send(tx)
    bad = GOOD[:-1] + bytes([GOOD[-1] ^ 0xFF])
    assert tx.received(bad, at + 0.03)
    retry = tx.next()
    assert isinstance(retry, Send) and retry.at == pytest.approx(at + 0.03 + FRAMING.silence)
    tx.sent(retry.at)
    assert tx.received(GOOD, retry.at + 0.03)
    done = tx.next()
    assert isinstance(done, Done) and done.frame == GOOD
    assert line.counts.late[3] == 0


def test_an_exception_reply_is_not_retried() -> None:
    tx = Transaction(fresh(), REQ, timeout=0.5, retries=3)
    at = send(tx)
    assert tx.received(ExceptionReply(3, 4, 2).frame(), at + 0.02)
    failed = tx.next()
    assert isinstance(failed, Failed) and (failed.kind, failed.code) == ("exception", 2)
    assert tx.attempts == 1


def test_a_broadcast_is_done_when_sent_and_gives_the_devices_time() -> None:
    line = fresh()
    write = with_crc(bytes((0, 6, 0, 1, 0, 5)))
    tx = Transaction(line, write, timeout=0.5, turnaround=0.1)
    at = send(tx)
    assert tx.next() == Done(b"", "broadcast")
    assert line.ready_at() >= at + FRAMING.wire_time(len(write)) + 0.1


def test_a_tolerated_write_without_echo_is_unconfirmed_not_failed() -> None:
    write = write_registers_request(3, 0x10, [1], function=6).frame()
    tx = Transaction(fresh(), write, timeout=0.1, tolerate=True)
    at = send(tx)
    tx.expired(at + tx.limit)
    assert tx.next() == Done(b"", "unconfirmed")


def test_requests_are_checked_before_anything_is_sent() -> None:
    with pytest.raises(Refused, match=r"1\.\.255"):
        read_request(0, Table.HOLDING, 0, 1)
    with pytest.raises(Refused, match=rf"1\.\.{MAX_QUANTITY[3]}"):
        read_request(1, Table.HOLDING, 0, MAX_QUANTITY[3] + 1)
    assert read_request(1, Table.COIL, 0, MAX_QUANTITY[1]) == ReadRequest(1, 1, 0, MAX_QUANTITY[1])
    assert write_coil_request(1, 7, True).frame() == WriteSingle(1, 5, 7, 1).frame()
    with pytest.raises(Refused):
        read_request(1, Table.COIL, 0, MAX_QUANTITY[1] + 1)
    with pytest.raises(Refused):
        read_request(1, Table.HOLDING, 0xFFFF, 2)  # past the end of the table
    with pytest.raises(Refused):
        write_registers_request(1, 0, [0x10000])
    with pytest.raises(Refused):
        write_registers_request(1, 0, [1] * (MAX_QUANTITY[16] + 1))
    with pytest.raises(Refused):
        write_registers_request(1, 0, [1, 2], function=6)
    with pytest.raises(Refused):
        write_coil_request(1, 0x10000, True)
    with pytest.raises(Refused, match="not a request"):
        pdu_frame(1, bytes((3, 0, 0)))  # too short for FC03
    assert pdu_frame(1, bytes((3, 0, 0, 0, 1))) == ReadRequest(1, 3, 0, 1).frame()
    with pytest.raises(Refused, match="make no sense"):
        Transaction(fresh(), REQ, timeout=0)
