"""RTU over TCP framing and its CRC (rtupoll.gateway.rtutcp)."""

from __future__ import annotations

import pytest

from rtupoll.gateway import mbap, rtutcp
from rtupoll.rtu import with_crc


def test_rtu_over_tcp_frames_and_crc() -> None:
    req = with_crc(bytes.fromhex("01 04 75 36 00 05"))
    dec = rtutcp.RtuDecoder()
    assert dec.feed(req[:3]) == []
    got = dec.feed(req[3:])
    assert [(f.tid, f.unit, f.pdu) for f in got] == [(None, 1, bytes.fromhex("04 75 36 00 05"))]
    assert rtutcp.encode(1, b"\x84\x02") == with_crc(b"\x01\x84\x02")
    with pytest.raises(mbap.MbapError, match="CRC"):
        rtutcp.RtuDecoder().feed(req[:-1] + bytes([req[-1] ^ 1]))
