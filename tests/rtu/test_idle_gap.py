"""The idle gap (rtupoll.rtu.line, ``Line.set_idle_gap``), in virtual time: a request to a
device that needs a longer silence than 3.5 characters waits for it, counted from the
last byte on the line, whoever sent it; other devices keep the 3.5 characters."""

from __future__ import annotations

import pytest

from rtupoll.rtu import Framing, Table, read_request, read_response
from rtupoll.rtu.line import Answer, Line
from rtupoll.rtu.transaction import Send, Transaction

FR = Framing(9600)


def req(unit: int, address: int = 0, count: int = 2) -> bytes:
    return read_request(unit, Table.HOLDING, address, count)


def reply(unit: int, count: int = 2) -> bytes:
    return read_response(unit, 3, list(range(count)))


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
