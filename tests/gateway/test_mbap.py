"""MBAP framing: a stream cut anywhere, frames it refuses, replies (rtupoll.gateway.mbap)."""

from __future__ import annotations

import struct

import pytest

from rtupoll.gateway import mbap


def frame(tid: int, unit: int, pdu: bytes, *, proto: int = 0, length: int | None = None
          ) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1 if length is None else length,
                       unit) + pdu


READ = bytes.fromhex("04 75 36 00 05")  # Huiwen: 5 input registers at 30006


def test_mbap_splits_a_stream_cut_anywhere() -> None:
    stream = frame(1, 3, READ) + frame(2, 4, bytes.fromhex("03 00 00 00 02")) + \
        frame(3, 3, bytes.fromhex("10 00 10 00 02 04 00 01 00 02"))
    for cut in range(1, len(stream)):
        dec = mbap.MbapDecoder()
        got = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        assert [(f.tid, f.unit, f.pdu[0]) for f in got] == [(1, 3, 4), (2, 4, 3), (3, 3, 16)]
        assert dec.buffer == b""


@pytest.mark.parametrize(("data", "why"), [
    (frame(1, 3, READ, proto=1), "protocol id 1"),
    (frame(1, 3, bytes([3]) + bytes(299)), "outside 2..254"),  # a 300-byte PDU
    (frame(1, 3, READ, length=1), "outside 2..254"),
    (frame(1, 3, READ + b"\x00\x00"), "does not match"),  # a read with 2 extra bytes
    (frame(1, 3, bytes.fromhex("10 00 10 00 02 04 00 01 00 02"), length=9) + b"\x00",
     "does not match"),
])
def test_mbap_refuses_frames_it_cannot_trust(data: bytes, why: str) -> None:
    with pytest.raises(mbap.MbapError, match=why):
        mbap.MbapDecoder().feed(data)


def test_mbap_reply_and_exception_encoding() -> None:
    assert mbap.encode(0x1234, 3, b"\x03\x02\x00\x07") == bytes.fromhex(
        "12 34 00 00 00 05 03 03 02 00 07")
    assert mbap.encode_exception(7, 9, 3, 0x0B) == bytes.fromhex("00 07 00 00 00 03 09 83 0b")
