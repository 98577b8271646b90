"""An adapter's echo without --echo, at wire speed (issue 47: recognised only when the echo
came back all at once), in virtual time: each byte of the request coming back as it
leaves the wire, 1.15 ms apart at 9600 baud, then the device's reply."""

from __future__ import annotations

import pytest

from rtupoll.rtu import Framing
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.line import ECHO_HINT, Answer, Garbled, Line
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.transaction import Await, Done, Failed, Send, Transaction

FR = Framing(9600)
REQUEST = ReadRequest(2, 3, 0x10, 5).frame()
REPLY = ReadReply(2, 3, (1, 2, 3, 4, 5)).frame()


def paced(line: Line, data: bytes, start: float) -> Answer | Garbled | None:
    """``data`` arriving one byte per character time from ``start``; the first event."""
    for i in range(len(data)):
        event = line.receive(data[i : i + 1], start + (i + 1) * FR.char_time)
        if event is not None:
            return event
    return None


def run(line: Line, request: bytes, *, retries: int = 2) -> tuple[Done | Failed, int]:
    """One transaction whose every attempt comes back byte by byte, then its reply 5 ms
    after the request's end (the bytes, as an echoing adapter hands them over); the
    outcome and the attempts it took."""
    tx = Transaction(line, request, timeout=0.5, retries=retries)
    now = 0.0
    while True:
        step = tx.next()
        if isinstance(step, Done | Failed):
            return step, tx.attempts
        if isinstance(step, Send):
            now = max(now, step.at)
            tx.sent(now)
            end = now + FR.wire_time(len(request))
            arriving = [(now + (i + 1) * FR.char_time, request[i : i + 1])
                        for i in range(len(request))]
            arriving += [(end + 0.005 + (i + 1) * FR.char_time, REPLY[i : i + 1])
                         for i in range(len(REPLY))]
            for at, byte in arriving:
                now = at
                if tx.received(byte, at):
                    break
            continue
        assert isinstance(step, Await)
        tx.expired(step.until)
        now = step.until


@pytest.mark.parametrize("paced_echo", [True, False], ids=["byte-by-byte", "all-at-once"])
def test_without_echo_an_echo_ends_the_first_attempt_with_the_hint_and_no_retry(
        paced_echo: bool) -> None:
    line = Line(FR)
    tx = Transaction(line, REQUEST, timeout=0.5, retries=2)
    step = tx.next()
    assert isinstance(step, Send)
    tx.sent(0.0)
    if paced_echo:
        for i in range(len(REQUEST) - 1):  # the request coming back: no verdict yet
            assert not tx.received(REQUEST[i : i + 1], (i + 1) * FR.char_time)
        assert tx.received(REQUEST[-1:], len(REQUEST) * FR.char_time)
    else:
        assert tx.received(REQUEST, len(REQUEST) * FR.char_time)
    outcome = tx.next()
    assert isinstance(outcome, Failed) and outcome.kind == "frame"
    assert outcome.why.endswith(ECHO_HINT)  # one try: a retry would come back the same
    assert tx.attempts == 1 and line.counts.echoes == 1 and line.echo_found
    assert line.counts.late[2] == 0 and line.counts.garbled[2] == 0  # an echo, not noise


def test_adopted_the_first_request_is_answered_and_the_next_ones_too() -> None:
    line = Line(FR)
    line.adopt_echo = True  # poll: carry on with the echo consumed
    line.send(REQUEST, 0.0)
    assert paced(line, REQUEST, 0.0) is None  # the whole echo: consumed, keep waiting
    assert line.echo and line.echo_found and line.counts.echoes == 1
    end = FR.wire_time(len(REQUEST))
    answer = paced(line, REPLY, end + 0.005)
    assert isinstance(answer, Answer) and answer.frame == REPLY
    # its reply time is the device's, from the request's end to the reply's first byte
    assert answer.reply_time == pytest.approx(0.005 + FR.char_time)
    assert line.counts.late[2] == 0 and line.counts.timeouts[2] == 0
    # from now on each echo is consumed as with --echo
    line.send(REQUEST, 1.0)
    assert paced(line, REQUEST, 1.0) is None
    assert isinstance(paced(line, REPLY, 1.0 + end + 0.005), Answer)
    assert line.counts.echoes == 1  # said once


def test_adopted_through_a_transaction_one_attempt_and_no_late() -> None:
    line = Line(FR)
    line.adopt_echo = True
    outcome, attempts = run(line, REQUEST)
    assert isinstance(outcome, Done) and outcome.frame == REPLY and attempts == 1
    assert line.counts.late[2] == 0 and line.counts.timeouts[2] == 0


def test_the_known_limit_a_write_echo_is_its_reply_until_an_echo_was_seen() -> None:
    """FC06's echo is byte for byte the device's confirmation: before any echo was seen on
    the line it is taken for it (a dead device's write looks confirmed: docs/polling.md);
    once one was, it is named."""
    line = Line(FR)
    write = with_crc(bytes((2, 6, 0, 0x10, 0, 7)))
    line.send(write, 0.0)
    assert paced(line, write, 0.0) == Answer(write)  # (the echo, taken for the reply)
    line.send(REQUEST, 1.0)
    event = paced(line, REQUEST, 1.0)
    assert isinstance(event, Garbled) and event.final
    line.send(write, 2.0)
    event = paced(line, write, 2.0)
    assert isinstance(event, Garbled) and event.why == ECHO_HINT
