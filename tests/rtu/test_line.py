"""The master's line discipline (rtupoll.rtu.line), in virtual time: no port, no clock.

Each test plays a script of what went out, what came in and when, and checks what the
line says: when the next frame may go, which frame is the answer, what is late.
"""

from __future__ import annotations

import random

import pytest

from rtupoll.rtu import Framing
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.line import LATE_FACTOR, Answer, Garbled, Line
from rtupoll.rtu.messages import ReadReply, ReadRequest


def reply(unit: int, first: int, count: int = 2) -> bytes:
    return ReadReply(unit, 3, tuple([first + i for i in range(count)])).frame()


def req(unit: int, address: int, count: int = 2) -> bytes:
    return ReadRequest(unit, 3, address, count).frame()


@pytest.mark.parametrize(("baud", "silence"), [(9600, 3.5 * 11 / 9600), (115200, 0.00175)])
def test_silence_after_a_reply_and_after_a_request(baud: int, silence: float) -> None:
    line = Line(Framing(baud, parity="E"))
    line.send(req(1, 0), 10.0)
    tx_end = 10.0 + 8 * 11 / baud
    assert line.ready_at() == pytest.approx(tx_end + silence)
    assert isinstance(line.receive(reply(1, 0), 10.05), Answer)
    assert line.ready_at() == pytest.approx(10.05 + silence)


def test_drain_after_a_timeout_waits_for_a_quiet_line() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    assert line.expire(0.5, 0.5) is None  # silence: a timeout
    assert line.ready_at() == pytest.approx(1.0)  # quiet for the timeout that expired
    line.receive(b"\xff", 0.8)  # noise: quiet counts from the last byte
    assert line.ready_at() == pytest.approx(1.3)
    assert line.ready_at(drain=False) == pytest.approx(0.8 + Framing(9600).silence)


def test_a_line_that_never_goes_quiet_does_not_hold_the_master_for_ever() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    line.expire(0.5, 0.5)
    for k in range(161):
        line.receive(b"\x00", 0.5 + 0.01 * k)  # a chattering line, up to 2.1 s
    # after three drain periods only the silence after the last byte is waited for
    assert line.ready_at() == pytest.approx(2.1 + Framing(9600).silence)


def test_stray_bytes_before_the_reply_are_skipped() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    assert line.receive(b"\x00\xff", 0.02) is None
    assert line.receive(reply(1, 0), 0.03) == Answer(reply(1, 0))


def test_a_slow_answer_is_the_answer_whoever_asks_about_the_unit_meanwhile() -> None:
    """A device that answers 100 ms after a request at 115200 baud (its settle window,
    a long frame's wire time, is 24 ms): another request to the unit waiting for the
    bus asks meanwhile whether it may go. The request in flight stays outstanding until
    its attempt ends, so its answer is its answer (it was dropped, the reply ignored as
    unsolicited, and the read timed out: seen in a suite run under load)."""
    line = Line(Framing(115200))
    a, b = req(1, 0), req(1, 2)
    line.send(a, 0.0)
    assert line.hazard_until(b, 0.05) <= 0.05  # the bus's lock, not the line, holds B
    assert line.receive(reply(1, 0), 0.1) == Answer(reply(1, 0))
    assert line.counts.unsolicited == 0


def test_a_wrong_id_frame_glued_to_the_right_one() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    assert line.receive(reply(7, 99) + reply(1, 0), 0.03) == Answer(reply(1, 0))
    assert line.counts.unsolicited == 1  # unit 7's frame answered nothing we asked


def test_a_reply_split_over_several_chunks() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    r = reply(1, 0)
    assert line.receive(r[:3], 0.02) is None
    assert line.receive(r[3:], 0.025) == Answer(r)


def test_a_garbled_reply_is_known_at_once() -> None:
    line = Line(Framing(9600))
    line.send(req(1, 0), 0.0)
    bad = bytearray(reply(1, 0))
    bad[4] ^= 0x40
    event = line.receive(bytes(bad), 0.02)
    assert isinstance(event, Garbled) and "CRC" in event.why
    assert line.attempt is None  # the attempt is over: retry after the silence


def _bad_crc(frame: bytes) -> bytes:
    bad = bytearray(frame)
    bad[-1] ^= 0x5A  # only the CRC is wrong, as on a noisy line's last bytes
    return bytes(bad)


def test_a_garbled_reply_settles_its_request_its_retry_is_never_late() -> None:
    """Issue 24.1: a complete frame with a bad CRC settles the attempt as garbled at once;
    the retry goes after the silence; its answer is the retry's, not late, and its reply
    time is the retry's own (the learned timeout never sees the garbled attempt)."""
    framing = Framing(9600)
    line = Line(framing)
    a = req(3, 0)
    line.send(a, 0.0)
    event = line.receive(_bad_crc(reply(3, 0)), 0.035)
    assert isinstance(event, Garbled)
    assert line.attempt is None
    retry_at = line.ready_at(drain=False)
    assert retry_at == pytest.approx(0.035 + framing.silence)  # the silence, no drain
    assert line.ready_at() == retry_at  # a garbled reply is no timeout: nothing to drain
    assert line.hazard_until(req(3, 10), retry_at) == 0  # a different read may go too
    line.send(a, retry_at)
    answer = line.receive(reply(3, 0), retry_at + 0.035)
    assert answer == Answer(reply(3, 0))
    assert line.counts.late[3] == 0 and line.counts.unsolicited == 0
    own = 0.035 - framing.wire_time(len(a))
    assert isinstance(answer, Answer) and answer.reply_time == pytest.approx(own)
    assert line.reply_time[3] == pytest.approx(own)
    assert 3 not in line.late_reply_time


def test_thirty_percent_crc_noise_is_garbled_never_late() -> None:
    """A device that answers every request in 12 ms through a line that garbles 30 % of
    the replies: every garbled reply is counted garbled, none late, and every reply
    time stays 12 ms (what the learned timeout is fed)."""
    framing, rng = Framing(9600), random.Random(24)
    line, now, garbled = Line(framing), 0.0, 0
    for k in range(300):
        request = req(3, 2 * (k % 4))
        for _attempt in range(4):
            now = max(now, line.ready_at(drain=False), line.hazard_until(request, now))
            line.send(request, now)
            good = reply(3, 2 * (k % 4))
            at = now + framing.wire_time(len(request)) + 0.012
            noisy = rng.random() < 0.3
            event = line.receive(_bad_crc(good) if noisy else good, at)
            now = at + framing.wire_time(len(good))
            if noisy:
                assert isinstance(event, Garbled)
                garbled += 1
                continue
            assert event == Answer(good)
            assert isinstance(event, Answer) and event.reply_time == pytest.approx(0.012)
            break
    assert garbled > 60
    assert line.counts.late[3] == 0 and not line.late_reply_time
    assert max(line.reply_time.values()) == pytest.approx(0.012)


def test_a_garbled_late_reply_of_a_timed_out_attempt_keeps_the_others_window() -> None:
    """Attempt 1 times out (its late window opens); attempt 2 of the same read gets a
    garbled frame: one of the two identical outstanding requests is settled, the other
    still holds a different read of that shape back, and the next answer is a right
    one (identical requests), never a different read's."""
    timeout = 0.1
    line = Line(Framing(9600))
    a, b = req(2, 0), req(2, 2)
    line.send(a, 0.0)
    assert line.expire(timeout, timeout) is None
    line.send(a, line.ready_at(drain=False) + 0.2)
    assert isinstance(line.receive(_bad_crc(reply(2, 0)), 0.35), Garbled)
    assert line.hazard_until(b, 0.4) >= LATE_FACTOR * timeout  # A may still be answered


@pytest.mark.parametrize("late_by", [1, 2, 3, 10])
def test_a_late_reply_is_never_the_next_requests_answer(late_by: int) -> None:
    """Read A times out; its reply comes ``late_by`` timeouts late. The next read, B,
    of the same shape, is held while A may still be answered, and when A's reply
    arrives it is counted late: B's answer is B's."""
    timeout = 0.1
    line = Line(Framing(9600))
    a, b = req(2, 0), req(2, 2)
    line.send(a, 0.0)
    assert line.expire(timeout, timeout) is None
    now = timeout + 0.05
    assert line.hazard_until(b, now) >= LATE_FACTOR * timeout  # B must not go yet
    assert line.hazard_until(a, now) == 0  # A again may: any answer to A is A's
    late_at = timeout * (1 + late_by)
    line.receive(reply(2, 1000), late_at)  # A's reply, late
    assert line.counts.late[2] == 1
    assert line.hazard_until(b, late_at) == 0  # A answered: B may go
    line.send(b, late_at + 0.01)
    assert line.receive(reply(2, 2000), late_at + 0.03) == Answer(reply(2, 2000))


def test_two_answers_while_a_different_request_is_outstanding_are_both_distrusted() -> None:
    """Sent anyway (the bus would have waited), B cannot take A's late reply: either
    frame may be A's (devices do not always answer in order), so neither is B's
    answer; B times out and is retried, never decoded from the wrong frame."""
    line = Line(Framing(9600))
    line.send(req(2, 0), 0.0)
    line.expire(0.1, 0.1)
    line.send(req(2, 2), 0.3)
    assert line.receive(reply(2, 1000), 0.35) is None  # A's late reply
    assert line.receive(reply(2, 2000), 0.36) is None  # B's answer, but which is which?
    assert line.counts.late[2] == 2


def test_a_reply_that_began_before_the_request_was_sent_is_not_its_answer() -> None:
    line = Line(Framing(9600))
    line.send(req(2, 0), 0.0)
    line.expire(0.1, 0.1)
    line.receive(reply(2, 1000)[:4], 0.29)  # A's late reply starts ...
    line.send(req(2, 0), 0.30)  # (a retry of A would be answered by it: harmless)
    line.send(req(2, 2), 0.31)
    assert line.receive(reply(2, 1000)[4:], 0.32) is None


def test_a_retry_takes_the_late_answer_of_its_own_first_attempt() -> None:
    line = Line(Framing(9600))
    a = req(2, 0)
    line.send(a, 0.0)
    line.expire(0.1, 0.1)
    line.send(a, 0.2)  # a retry of the same request
    assert line.receive(reply(2, 1000), 0.25) == Answer(reply(2, 1000))
    # the retry's own answer may still come: a different read must wait for it ...
    assert line.hazard_until(req(2, 2), 0.26) > 0.26
    line.receive(reply(2, 1000), 0.27)  # ... and when it comes, it is late, not B's
    assert line.hazard_until(req(2, 2), 0.28) == 0
    assert line.counts.late[2] == 2  # both came after the first attempt had timed out


def test_exception_replies_are_matched_like_any_answer() -> None:
    line = Line(Framing(9600))
    line.send(req(3, 0), 0.0)
    exc = with_crc(bytes((3, 0x83, 2)))
    assert line.receive(exc, 0.02) == Answer(exc)


def test_other_units_are_not_held_by_a_late_device() -> None:
    line = Line(Framing(9600))
    line.send(req(2, 0), 0.0)
    line.expire(0.1, 0.1)
    assert line.hazard_until(req(3, 0), 0.2) == 0


def test_random_late_replies_never_give_a_wrong_answer() -> None:
    """A device that answers each request once, in order, some of them late by up to
    ten timeouts; a master that obeys ``hazard_until`` and reads different blocks of
    one shape. Every answer taken carries the block it was asked for."""
    rnd = random.Random(4)
    timeout, line = 0.1, Line(Framing(9600))
    now, wrong, right = 0.0, 0, 0
    pending: list[tuple[float, bytes]] = []  # the device's replies: (arrival time, frame)
    for _ in range(300):
        address = 2 * rnd.randrange(50)
        request = req(2, address)
        while True:  # wait as the bus does; replies keep arriving meanwhile
            while pending and pending[0][0] <= now:
                at, frame = pending.pop(0)
                assert line.receive(frame, at) is None  # nothing is awaited
            ready = max(line.hazard_until(request, now), line.ready_at())
            if ready <= now:
                break
            now = min(ready, pending[0][0]) if pending else ready
        delay = rnd.choice([0.01, 0.01, 0.01, 1.5 * timeout, 3 * timeout, 10 * timeout])
        line.send(request, now)
        pending.append((max([now + delay] + [t for t, _ in pending]), reply(2, address * 100)))
        deadline, answer = now + timeout, None
        while pending and pending[0][0] <= deadline and answer is None:
            at, frame = pending.pop(0)
            event = line.receive(frame, max(at, now))
            if isinstance(event, Answer):
                answer = event.frame
        if answer is None:
            line.expire(deadline, timeout)
            now = deadline
            continue
        if answer == reply(2, address * 100):
            right += 1
        else:
            wrong += 1
    assert wrong == 0
    assert right > 100
    assert sum(line.counts.late.values()) > 0


# -- issue 24.4: adapters that echo ----------------------------------------------------


def test_echo_on_the_echo_is_consumed_and_the_reply_is_the_answer() -> None:
    framing = Framing(9600)
    line = Line(framing, echo=True)
    a = req(1, 0)
    line.send(a, 0.0)
    assert line.receive(a[:3], 0.004) is None  # the echo, in chunks, while a goes out
    assert line.receive(a[3:], 0.009) is None
    answer = line.receive(reply(1, 0), 0.03)
    assert answer == Answer(reply(1, 0))
    assert line.counts.unsolicited == 0 and line.counts.late[1] == 0
    # the reply time is still counted from the end of the request, not from the echo
    assert isinstance(answer, Answer)
    assert answer.reply_time == pytest.approx(0.03 - framing.wire_time(len(a)))


def test_echo_on_an_echo_and_the_reply_in_one_chunk() -> None:
    line = Line(Framing(9600), echo=True)
    w = with_crc(bytes((1, 6, 0, 5, 0, 42)))  # FC06: the echo is the reply's very bytes
    line.send(w, 0.0)
    assert line.receive(w + w, 0.03) == Answer(w)


def test_echo_on_a_write_to_a_dead_device_is_not_confirmed_by_its_echo() -> None:
    line = Line(Framing(9600), echo=True)
    w = with_crc(bytes((1, 6, 0, 5, 0, 42)))
    line.send(w, 0.0)
    assert line.receive(w, 0.01) is None  # only the echo: the device is silent
    assert line.expire(0.2, 0.2) is None  # a timeout, not an answer


def test_echo_on_an_echo_that_differs_garbles_the_attempt() -> None:
    line = Line(Framing(9600), echo=True)
    a = req(1, 0)
    line.send(a, 0.0)
    bad = bytes((a[0], a[1] ^ 0x10)) + a[2:]
    event = line.receive(bad, 0.01)
    assert isinstance(event, Garbled) and "echo differs" in event.why
    assert line.attempt is None


def test_echo_on_an_adapter_that_does_not_echo_is_said_so() -> None:
    line = Line(Framing(9600), echo=True)
    line.send(req(1, 0), 0.0)
    event = line.receive(reply(1, 0), 0.03)
    assert isinstance(event, Garbled) and "drop --echo" in event.why


def test_echo_off_an_echo_is_detected_and_named_never_an_answer() -> None:
    line = Line(Framing(9600))
    a = req(1, 0)
    line.send(a, 0.0)
    assert line.receive(a[:4], 0.004) is None  # part of the request: wait for the rest
    event = line.receive(a[4:] + reply(1, 0), 0.03)
    assert isinstance(event, Garbled) and "--echo" in event.why
    assert line.counts.echoes == 1
    # once seen, a write's echo (byte for byte its reply) is not a confirmation either
    w = with_crc(bytes((1, 6, 0, 5, 0, 42)))
    line.send(w, 1.0)
    event = line.receive(w, 1.01)
    assert isinstance(event, Garbled) and "--echo" in event.why


def test_echo_off_a_write_reply_equal_to_the_request_is_the_answer() -> None:
    line = Line(Framing(9600))  # no echo seen: FC06's reply is the request's bytes
    w = with_crc(bytes((1, 6, 0, 5, 0, 42)))
    line.send(w, 0.0)
    assert line.receive(w[:5], 0.02) is None
    assert line.receive(w[5:], 0.021) == Answer(w)
