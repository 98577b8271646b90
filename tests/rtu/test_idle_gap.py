"""The idle gap (rtupoll.rtu.line, ``Line.set_idle_gap``, named by a request:
``Transaction(idle_gap=)``), in virtual time: a request to a device that needs a longer
silence than 3.5 characters waits for it, counted from the last byte on the line,
whoever sent it; other devices keep the 3.5 characters."""

from __future__ import annotations

import pytest

from rtupoll.rtu import Framing
from rtupoll.rtu.line import GAP_HALF_LIFE, GAP_MAX, GAP_STEP, Answer, Line
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.transaction import Send, Transaction

FR = Framing(9600)


def req(unit: int, address: int = 0, count: int = 2) -> bytes:
    return ReadRequest(unit, 3, address, count).frame()


def reply(unit: int, count: int = 2) -> bytes:
    return ReadReply(unit, 3, tuple(list(range(count)))).frame()


def test_a_unit_with_a_gap_waits_for_it_after_any_devices_last_byte() -> None:
    line = Line(FR)
    line.set_idle_gap(3, 0.05)
    line.send(req(7), 10.0)  # the radar's request and reply
    assert isinstance(line.receive(reply(7), 10.03), Answer)
    assert line.ready_at(unit=7) == pytest.approx(10.03 + FR.silence)  # no gap: 3.5 chars
    assert line.ready_at(unit=3) == pytest.approx(10.03 + 0.05)  # from the radar's reply
    assert line.ready_at() == pytest.approx(10.03 + FR.silence)  # no unit named: the silence
    line.receive(b"\x00", 10.07)  # a stray byte: the gap starts again from it
    assert line.ready_at(unit=3) == pytest.approx(10.12)


def test_the_gap_counts_from_the_end_of_a_request_nobody_answered() -> None:
    line = Line(FR)
    line.set_idle_gap(3, 0.05)
    line.send(req(9), 1.0)
    line.expire(1.5, 0.5)
    assert line.ready_at(unit=3, drain=False) == pytest.approx(1.0 + FR.wire_time(8) + 0.05)


def test_the_lines_gap_applies_to_every_unit_and_a_units_own_may_be_longer() -> None:
    line = Line(FR, idle_gap=0.02)
    line.set_idle_gap(3, 0.05)
    line.set_idle_gap(4, 0.01)  # shorter than the line's: the line's
    line.send(req(1), 0.0)
    line.receive(reply(1), 0.02)
    assert line.ready_at(unit=1) == pytest.approx(0.04)
    assert line.ready_at(unit=4) == pytest.approx(0.04)
    assert line.ready_at(unit=3) == pytest.approx(0.07)
    line.set_idle_gap(3, 0.0)  # taken back
    assert line.ready_at(unit=3) == pytest.approx(0.04)


def test_a_gap_shorter_than_the_silence_changes_nothing() -> None:
    line = Line(FR)
    line.set_idle_gap(3, FR.silence / 2)
    line.send(req(1), 0.0)
    line.receive(reply(1), 0.02)
    assert line.ready_at(unit=3) == line.ready_at(unit=1) == pytest.approx(0.02 + FR.silence)


def test_a_transaction_sends_its_first_attempt_and_retries_after_the_gap() -> None:
    line = Line(FR)
    line.set_idle_gap(3, 0.85)  # Growatt: "wait at least 850 ms between commands"
    line.send(req(7), 0.0)
    line.receive(reply(7), 0.03)
    tx = Transaction(line, req(3), timeout=0.5, retries=1)
    step = tx.next()
    assert isinstance(step, Send) and step.at == pytest.approx(0.88)
    tx.sent(step.at)
    tx.expired(tx.deadline)
    retry = tx.next()
    assert isinstance(retry, Send)
    assert retry.at == pytest.approx(step.at + FR.wire_time(8) + 0.85)


def test_a_request_names_its_units_gap_and_the_line_keeps_it_for_the_units_next() -> None:
    """The gap goes with the request (``Transaction(idle_gap=)``); a later request to the
    unit that names none (a gateway's pass-through) waits as long; one naming 0 takes it
    back."""
    line = Line(FR)

    def first_send(gap: float | None, at: float) -> float:
        line.send(req(7), at)
        line.receive(reply(7), at + 0.03)
        step = Transaction(line, req(3), timeout=0.5, idle_gap=gap).next()
        assert isinstance(step, Send)
        line.send(step.frame, step.at)
        line.receive(reply(3), step.at + 0.03)
        return step.at - (at + 0.03)  # the silence it went after

    assert first_send(0.05, 0.0) == pytest.approx(0.05)
    assert first_send(None, 1.0) == pytest.approx(0.05)  # kept for the unit
    assert first_send(0.0, 2.0) == pytest.approx(FR.silence)  # taken back
    assert first_send(None, 3.0) == pytest.approx(FR.silence)


# -- learned ------------------------------------------------------------------------------

def unheard_then_answered(line: Line, at: float, request: bytes) -> Answer:
    """One transaction: the first attempt goes right after the radar's reply and hears
    nothing; the retry, after the timeout's silence, is answered 5 ms after it ends."""
    line.send(req(7), at)
    assert isinstance(line.receive(reply(7), at + 0.03), Answer)
    first = line.ready_at(unit=request[0])
    line.send(request, first)
    assert line.expire(first + 0.5, 0.5) is None  # nothing at all: a timeout
    retry = max(first + 0.5, line.ready_at(drain=False, unit=request[0]))
    line.send(request, retry, retry=True)
    answer = line.receive(reply(3), retry + FR.wire_time(8) + 0.005)
    assert isinstance(answer, Answer)
    return answer


def test_a_device_that_hears_only_retries_after_a_long_silence_gets_a_gap_not_a_timeout(
        ) -> None:
    line = Line(FR)
    answer = unheard_then_answered(line, 0.0, req(3))
    # the answer is the retry's: its reply time counted from the retry, not late
    assert answer.reply_time == pytest.approx(0.005)
    assert line.counts.late[3] == 0 and line.learned_gap == {}  # once: not yet a gap
    answer = unheard_then_answered(line, 2.0, req(3))
    assert answer.reply_time == pytest.approx(0.005) and line.counts.late[3] == 0
    # twice: the gap is twice the silence that was not enough (at least GAP_STEP)
    assert line.learned_gap == {3: pytest.approx(GAP_STEP)}
    assert line.counts.gap_raised[3] == 1
    line.send(req(7), 4.0)
    line.receive(reply(7), 4.03)
    assert line.ready_at(unit=3) == pytest.approx(4.03 + GAP_STEP)
    assert line.ready_at(unit=7) == pytest.approx(4.03 + FR.silence)  # the others: as before
    unheard_then_answered(line, 6.0, req(3))  # still not enough: doubled
    assert line.learned_gap == {3: pytest.approx(2 * GAP_STEP, rel=1e-3)}


def test_a_learned_gap_is_bounded_and_halves_with_time() -> None:
    line = Line(FR)
    for k in range(12):
        unheard_then_answered(line, 2.0 * k, req(3))
    # the retry's silence worked and bounds it; GAP_MAX bounds it too
    assert GAP_STEP < line.learned_gap[3] <= min(GAP_MAX, 0.5 + FR.wire_time(8))
    top = line.learned_gap[3]
    line.send(req(3), 24.0 + GAP_HALF_LIFE)
    assert line.learned_gap[3] == pytest.approx(top / 2, rel=0.01)
    line.send(req(3), 24.0 + 20 * GAP_HALF_LIFE)
    assert line.learned_gap == {}  # below the silence: gone
    assert line.ready_at(unit=3) == pytest.approx(line.ready_at(unit=7))


def test_an_attempt_taken_for_unheard_that_is_answered_after_all_is_late_and_no_gap() -> None:
    """A slow device, not a deaf one: the first attempt's answer comes after the retry's."""
    line = Line(FR)
    unheard_then_answered(line, 0.0, req(3))  # first attempt sent at about 0.034
    assert line.receive(reply(3), 0.9) is None  # ... and here is its answer, late
    assert line.counts.late[3] == 1
    assert line.late_reply_time[3] > 0.5
    for k in range(1, 4):  # the pattern again: no gap is learned for a while
        unheard_then_answered(line, 2.0 * k, req(3))
    assert line.learned_gap == {}


def test_no_gap_when_the_first_attempt_had_as_long_a_silence_as_the_retry() -> None:
    line = Line(FR)
    for k in range(3):
        at = 10.0 * k
        line.send(req(3), at)  # alone on the line, after a long pause
        line.expire(at + 0.5, 0.5)
        line.send(req(3), at + 0.5 + FR.silence, retry=True)
        line.receive(reply(3), at + 0.53)
    assert line.learned_gap == {}
    assert line.counts.late[3] == 3  # the old rule: a late answer to the first attempt
