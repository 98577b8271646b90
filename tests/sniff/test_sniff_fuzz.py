"""A listener survives any byte sequence: ``sniff``'s whole path (the splitter, the
pairing, the per-device view that decodes values, the one-line render) fed random
bytes and mutated traffic (bit flips, cuts, insertions, and odd frames with a valid
CRC: reads of 126-2000 registers, unknown functions, byte counts that lie), in chunks
of any size and timing. Every byte fed comes back in exactly one frame; a value is
only ever decoded from a CRC-valid reply."""

from __future__ import annotations

import struct
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rtupoll.config.library import load_library, load_one
from rtupoll.rtu import Framing, Table, crc_ok, with_crc
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.stream import Transaction
from rtupoll.sniff.lines import frame_line
from rtupoll.sniff.model import BusView, Known
from rtupoll.sniff.session import Session

F9600 = Framing(9600)
CHAR = F9600.char_time
LIBRARY = list(load_library(()).profiles.values())
KNOWN = [Known("air", load_one("huiwen-aq"), 3), Known("gas", load_one("net-irnet-pro"), 1),
         Known("meter", load_one("eastron-sdm120"), 10)]


# the strategies are built once: one built inside a strategy is built and checked again
# at every draw (that and a draw per byte were three quarters of this test's time)
UNITS = st.sampled_from([0, 1, 3, 10, 247, 255])
KINDS = st.sampled_from(["read", "reply", "huge", "exception", "any", "write"])
TABLES = st.sampled_from(list(Table))
U8, U16 = st.integers(0, 255), st.integers(0, 0xFFFF)


@st.composite
def frames(draw: st.DrawFn) -> bytes:
    """One frame as a master or a device could send it, or one that passes the CRC
    without making sense."""
    unit, kind = draw(UNITS), draw(KINDS)
    if kind == "read":
        fc, address = draw(TABLES).read_function, draw(U16)
        return ReadRequest(unit, fc, address, draw(st.integers(1, 125))).frame()
    if kind == "reply":
        n = draw(st.integers(0, 125))
        words = draw(st.binary(min_size=2 * n, max_size=2 * n))
        fc = draw(st.sampled_from([3, 4]))
        return ReadReply(unit, fc, struct.unpack(f">{n}H", words)).frame()
    if kind == "huge":  # more than any reply can carry: 126..0xFFFF registers
        return with_crc(struct.pack(">BBHH", unit, draw(st.sampled_from([1, 2, 3, 4])),
                                    draw(U16), draw(st.integers(126, 0xFFFF))))
    if kind == "exception":
        return with_crc(bytes((unit, draw(U8) | 0x80, draw(U8))))
    if kind == "write":
        return with_crc(struct.pack(">BBHH", unit, draw(st.sampled_from([5, 6, 8])),
                                    draw(U16), draw(U16)))
    return with_crc(bytes((unit, draw(U8))) + draw(st.binary(max_size=40)))


MUTATIONS = st.sampled_from(["keep", "keep", "flip", "cut", "insert", "recrc"])


@st.composite
def mutated(draw: st.DrawFn, frame: bytes) -> bytes:
    how = draw(MUTATIONS)
    data = bytearray(frame)
    if how == "flip" and data:
        i = draw(st.integers(0, len(data) - 1))
        data[i] ^= 1 << draw(st.integers(0, 7))
    elif how == "cut" and len(data) > 1:
        data = data[: draw(st.integers(1, len(data) - 1))]
    elif how == "insert":
        i = draw(st.integers(0, len(data)))
        data[i:i] = draw(st.binary(min_size=1, max_size=4))
    elif how == "recrc" and len(data) > 3:  # edited, and the CRC made valid again
        i = draw(st.integers(0, len(data) - 3))
        data[i] = draw(U8)
        data = bytearray(with_crc(bytes(data[:-2])))
    return bytes(data)


CHUNK, LATE = st.integers(1, 64), st.sampled_from([0.0, 0.016])


@st.composite
def traffic(draw: st.DrawFn) -> list[tuple[bytes, float]]:
    """Chunks with arrival times: mutated frames glued or apart, or plain random bytes."""
    if draw(st.booleans()):
        wire = b"".join([draw(mutated(draw(frames()))) for _ in range(draw(st.integers(1, 10)))])
        choices: tuple[float, ...] = (0.0, F9600.silence, 0.02, 1.5)
    else:
        wire = draw(st.binary(min_size=1, max_size=600))
        choices = (0.0, 0.0, F9600.silence)
    # the gap before each byte, one of the choices (a byte of one draw each)
    picks = draw(st.binary(min_size=len(wire), max_size=len(wire)))
    gaps = [choices[b % len(choices)] for b in picks]
    chunks, i, t = [], 0, 0.0
    while i < len(wire):
        n = draw(CHUNK)
        t += sum(gaps[i : i + n]) + n * CHAR + draw(LATE)
        chunks.append((wire[i : i + n], t))
        i += n
    return chunks


# 100 examples by default (7 CPU-s for 300), the long profile's 2,000 on demand
@settings(max_examples=max(100, settings().max_examples), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(traffic())
def test_the_sniffer_survives_any_bytes_and_accounts_for_every_one(
        chunks: list[tuple[bytes, float]]) -> None:
    view = BusView(KNOWN, LIBRARY)
    seen: list[Transaction] = []
    lines: list[str] = []

    def sink(tx: Transaction, records: list[dict[str, Any]]) -> None:
        seen.append(tx)
        lines.append(frame_line(tx, view, records))
        for r in records:  # a value is only ever decoded from a CRC-valid reply
            if r.get("value") is not None:
                assert tx.status == "ok" and tx.reply is not None and crc_ok(tx.reply.data)

    session = Session(F9600, view, sink)
    for data, t in chunks:
        session.feed(data, t)
        session.feed(b"", t + 0.05)
    session.close()
    fed = b"".join(d for d, _ in chunks)
    back = sum(len(f.data) for tx in seen for f in (tx.request, tx.reply, tx.junk)
               if f is not None)
    assert back == len(fed)
    assert all(isinstance(x, str) and "\n" not in x for x in lines)


def test_a_crc_valid_read_of_128_registers_is_a_request_answered_only_by_an_exception(
        ) -> None:
    huge = with_crc(struct.pack(">BBHH", 1, 3, 0, 128))
    seen: list[Transaction] = []
    view = BusView(KNOWN, LIBRARY)
    session = Session(F9600, view, lambda tx, recs: seen.append(tx))
    session.feed(huge, 1.0)
    session.feed(with_crc(bytes((1, 0x83, 2))), 1.01)
    session.feed(huge, 1.1)
    session.close()
    assert [tx.status for tx in seen] == ["exception", "timeout"]
