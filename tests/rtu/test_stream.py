"""The sniffer's sans-IO core: a tapped byte stream -> frames -> transactions, in virtual time.

Times are plain numbers (seconds); nothing here sleeps or opens a port.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from rtupoll.rtu import Framing, with_crc
from rtupoll.rtu.functions import Table
from rtupoll.rtu.messages import ExceptionReply, Malformed, ReadReply, ReadRequest, WriteSingle
from rtupoll.rtu.stream import Stream, Transaction

F9600 = Framing(9600)
CHAR = F9600.char_time  # ~1.15 ms
REQ = ReadRequest(3, 4, 0x7536, 2).frame()
REPLY = ReadReply(3, 4, (25, 50)).frame()


def run(chunks: list[tuple[bytes, float]], *, end: float | None = None,
        framing: Framing = F9600, **options: float) -> list[Transaction]:
    s = Stream(framing, **options)
    out: list[Transaction] = []
    for data, t in chunks:
        out += s.feed(data, t)
    if end is not None:
        out += s.tick(end)
    return out + s.close()


def on_wire(frame: bytes, start: float) -> tuple[bytes, float]:
    """A frame as one chunk, arriving when its last byte is complete."""
    return frame, start + len(frame) * CHAR


def test_request_and_reply_pair_with_the_reply_time() -> None:
    out = run([on_wire(REQ, 0.0), on_wire(REPLY, 0.030)])
    assert [t.status for t in out] == ["ok"]
    t = out[0]
    assert t.request is not None and t.request.data == REQ
    assert t.reply is not None and t.reply.data == REPLY
    assert t.unit == 3 and t.function == 4
    # request ends at 8 chars; the reply starts at 30 ms
    assert t.reply_time is not None and abs(t.reply_time - (0.030 - 8 * CHAR)) < 1e-6


def test_a_pause_inside_a_frame_does_not_split_it() -> None:
    # a slow USB adapter hands over 4 bytes, then the rest 16 ms later
    end = 0.030 + 4 * CHAR
    out = run([on_wire(REQ, 0.0), (REPLY[:4], end), (REPLY[4:], end + 0.016)])
    assert [t.status for t in out] == ["ok"]
    assert out[0].reply is not None and out[0].reply.data == REPLY


def test_two_frames_glued_without_a_gap_come_apart() -> None:
    out = run([(REQ + REPLY + REQ + REPLY, 0.05)])
    assert [t.status for t in out] == ["ok", "ok"]
    assert all(t.reply is not None and t.reply.data == REPLY for t in out)


def test_byte_by_byte_arrival_gives_the_same_transactions() -> None:
    wire = REQ + REPLY
    out = run([(wire[i : i + 1], (i + 1) * CHAR) for i in range(len(wire))])
    assert [t.status for t in out] == ["ok"]


def test_a_request_whose_first_bytes_make_a_valid_reply_is_still_a_request() -> None:
    """Unit 0x51, read 10 holding registers at 0x02B8: its first seven bytes happen to
    be a CRC-valid reply (byte count 2). Arriving byte by byte, it must not be cut there
    (found by the chunking property below)."""
    req = ReadRequest(0x51, 3, 0x02B8, 10).frame()
    assert req == bytes.fromhex("51 03 02 b8 00 0a 48 00")
    wire = req + ReadReply(0x51, 3, tuple([0] * 10)).frame()
    out = run([(wire[i : i + 1], (i + 1) * CHAR) for i in range(len(wire))])
    assert [t.status for t in out] == ["ok"]
    assert out[0].request is not None and out[0].request.data == req


def test_a_stray_byte_before_the_reply_is_noise_and_the_reply_still_counts() -> None:
    out = run([on_wire(REQ, 0.0), on_wire(b"\x00" + REPLY, 0.03)])
    assert [t.status for t in out] == ["noise", "ok"]
    assert out[0].junk is not None and out[0].junk.data == b"\x00"


def test_a_crc_error_in_the_reply_is_garbled_and_carries_no_value() -> None:
    bad = REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])
    out = run([on_wire(REQ, 0.0), on_wire(bad, 0.03)], end=0.5)
    assert [t.status for t in out] == ["garbled"]
    assert "CRC" in out[0].note


def test_a_truncated_reply_is_garbled_once_the_line_stays_quiet() -> None:
    out = run([on_wire(REQ, 0.0), on_wire(REPLY[:5], 0.03)], end=0.5)
    assert [t.status for t in out] == ["garbled"]
    assert "truncated" in out[0].note


def test_no_reply_within_the_timeout_is_a_timeout() -> None:
    s = Stream(F9600, timeout=0.5)
    assert s.feed(*on_wire(REQ, 0.0)) == []
    assert s.tick(0.3) == []
    out = s.tick(0.6)
    assert [t.status for t in out] == ["timeout"]


def test_the_next_request_ends_the_wait_and_a_late_reply_answers_nothing() -> None:
    other = ReadRequest(4, 4, 1, 1).frame()
    out = run([on_wire(REQ, 0.0), on_wire(other, 0.3), on_wire(REPLY, 0.31)], end=2.0)
    assert [t.status for t in out] == ["timeout", "orphan", "timeout"]
    assert out[1].reply is not None and out[1].reply.data == REPLY
    assert out[2].request is not None and out[2].request.data == other


def test_an_exception_reply_is_reported_with_its_code() -> None:
    out = run([on_wire(REQ, 0.0), on_wire(ExceptionReply(3, 4, 2).frame(), 0.03)])
    assert [t.status for t in out] == ["exception"]
    assert out[0].exception == 2 and "ILLEGAL DATA ADDRESS" in out[0].note


def test_a_write_echo_is_its_reply_and_a_broadcast_waits_for_nothing() -> None:
    write = WriteSingle(3, 6, 0x9C41, 7).frame()
    broadcast = WriteSingle(0, 6, 0x9C41, 7).frame()
    out = run([on_wire(write, 0.0), on_wire(write, 0.02), on_wire(broadcast, 0.1)])
    assert [t.status for t in out] == ["ok", "broadcast"]


def test_a_reply_from_another_unit_does_not_answer_the_request() -> None:
    wrong = ReadReply(9, 4, (25, 50)).frame()
    out = run([on_wire(REQ, 0.0), on_wire(wrong, 0.03)], end=2.0)
    assert [t.status for t in out] == ["orphan", "timeout"]


def test_garbage_between_transactions_is_reported_and_does_not_eat_frames() -> None:
    junk = bytes([0x55, 0x13, 0x99, 0x42, 0x17])
    out = run([on_wire(junk, 0.0), on_wire(REQ, 0.05), on_wire(REPLY, 0.07)])
    assert [t.status for t in out] == ["broken", "ok"]


def test_a_coil_read_reply_of_eight_bytes_is_taken_as_the_reply() -> None:
    req = with_crc(bytes([1, 1, 0, 0, 0, 20]))
    reply = with_crc(bytes([1, 1, 3, 0xFF, 0x0F, 0x05]))
    out = run([on_wire(req, 0.0), on_wire(reply, 0.02)])
    assert [t.status for t in out] == ["ok"]


def test_high_speed_uses_the_fixed_silence() -> None:
    fast = Framing(115200)
    c = fast.char_time
    out = run([(REQ, 8 * c), (REPLY, 0.004 + 17 * c)], framing=fast)
    assert [t.status for t in out] == ["ok"]


def test_a_reply_whose_length_the_standard_leaves_open_is_found_by_its_crc() -> None:
    req = with_crc(bytes([1, 0x2B, 0x0E, 0x01, 0x00]))  # read device identification
    reply = with_crc(bytes([1, 0x2B, 0x0E, 0x01, 0x01, 0x00, 0x00, 0x01, 0x00, 0x03])
                     + b"ACME")
    out = run([on_wire(req, 0.0), on_wire(reply, 0.02)])
    assert [t.status for t in out] == ["ok"]
    assert out[0].reply is not None and out[0].reply.data == reply


@st.composite
def traffic(draw: st.DrawFn) -> tuple[list[tuple[bytes, bytes]], list[tuple[bytes, float]]]:
    """Reads and their replies, on the wire back to back or after a silence, delivered in
    chunks of any size, each up to 16 ms late (a USB adapter's latency timer)."""
    exchanges = []
    for _ in range(draw(st.integers(1, 8))):
        unit = draw(st.integers(1, 247))
        table = draw(st.sampled_from([Table.INPUT, Table.HOLDING]))
        count = draw(st.integers(1, 12))
        words = draw(st.lists(st.integers(0, 0xFFFF), min_size=count, max_size=count))
        address = draw(st.integers(0, 0xFFF0))
        exchanges.append((ReadRequest(unit, table.read_function, address, count).frame(),
                          ReadReply(unit, table.read_function, tuple(words)).frame()))
    wire, times, t = b"", [], 0.0
    for request, reply in exchanges:
        for frame in (request, reply):
            t += draw(st.sampled_from([0.0, F9600.silence, 0.02]))  # glued, or a gap
            for _ in frame:
                t += CHAR
                times.append(t)
            wire += frame
    chunks, i, late = [], 0, 0.0
    while i < len(wire):
        n = draw(st.integers(1, 16))
        late = max(late, times[min(i + n, len(wire)) - 1] + draw(st.sampled_from([0, 0.016])))
        chunks.append((wire[i : i + n], late))
        i += n
    return exchanges, chunks


@given(traffic())
def test_any_chunking_and_gaps_give_back_every_transaction(
        case: tuple[list[tuple[bytes, bytes]], list[tuple[bytes, float]]]) -> None:
    exchanges, chunks = case
    out = run(chunks)
    assert [t.status for t in out] == ["ok"] * len(exchanges)
    assert [(t.request.data if t.request else b"", t.reply.data if t.reply else b"")
            for t in out] == exchanges


def test_a_transaction_carries_its_request_and_reply_as_messages() -> None:
    [ok] = run([on_wire(REQ, 0.0), on_wire(REPLY, 0.030)])
    assert ok.asked == ReadRequest(3, 4, 0x7536, 2)
    assert ok.answer(ok.asked) == ReadReply(3, 4, (25, 50))
    [refused] = run([on_wire(REQ, 0.0), on_wire(ExceptionReply(3, 4, 2).frame(), 0.03)])
    assert refused.asked == ReadRequest(3, 4, 0x7536, 2) and refused.answer(refused.asked) is None
    [lost] = run([on_wire(REQ, 0.0)])
    assert lost.status == "timeout" and lost.answer(lost.asked) is None
    big = with_crc(bytes.fromhex("03 04 00 00 00 C8"))  # 200 registers: refused by the parser
    [odd] = run([on_wire(big, 0.0)])
    assert isinstance(odd.asked, Malformed) and "quantity 200" in odd.asked.reason
