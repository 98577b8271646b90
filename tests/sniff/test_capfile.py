"""Capture files: pcapng with link type 250 (RTAC serial), read back exactly; pcap read too."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from rtupoll.errors import UsageError
from rtupoll.rtu import Framing
from rtupoll.sniff.capfile import LINKTYPE_RTAC_SERIAL, CaptureWriter, read_capture

CHUNKS = [(1_700_000_000.123456, bytes.fromhex("0104 7536 0005 ca0b")),
          (1_700_000_000.150001, bytes.fromhex("01040a00190032")),
          (1_700_000_000.151250, bytes.fromhex("00fa138800003994")),
          (1_700_000_001.0, b"\x00")]


def test_chunks_and_line_settings_come_back_as_written(tmp_path: Path) -> None:
    path = tmp_path / "cap.pcapng"
    w = CaptureWriter(path, Framing(19200, 8, "E", 1), "/dev/ttyUSB0")
    for t, data in CHUNKS:
        w.write(data, t)
    w.close()
    cap = read_capture(path)
    assert cap.framing == Framing(19200, 8, "E", 1)
    assert cap.port == "/dev/ttyUSB0"
    assert [d for _, d in cap.chunks] == [d for _, d in CHUNKS]
    assert all(abs(a - b) < 1e-6 for (a, _), (b, _) in zip(cap.chunks, CHUNKS, strict=True))


def test_the_file_is_pcapng_with_an_rtac_serial_interface(tmp_path: Path) -> None:
    """What Wireshark reads: a section header, an interface of link type 250 with the
    baud rate as if_speed, and packets whose payload is the 12-byte RTAC header
    (big-endian arrival seconds and microseconds) followed by the bytes."""
    path = tmp_path / "cap.pcapng"
    w = CaptureWriter(path, Framing(9600), "/dev/ttyUSB0")
    w.write(CHUNKS[0][1], CHUNKS[0][0])
    w.close()
    raw = path.read_bytes()
    kind, shb_len, magic = struct.unpack("<III", raw[:12])
    assert (kind, magic) == (0x0A0D0D0A, 0x1A2B3C4D)
    idb = raw[shb_len:]
    kind, idb_len, link = struct.unpack("<IIH", idb[:10])
    assert (kind, link) == (1, LINKTYPE_RTAC_SERIAL)
    assert struct.pack("<HHQ", 8, 8, 9600) in idb[:idb_len]  # if_speed
    epb = idb[idb_len:]
    kind, _, iface, _, _, caplen = struct.unpack("<IIIIII", epb[:24])
    assert (kind, iface, caplen) == (6, 0, 12 + len(CHUNKS[0][1]))
    seconds, micros, event = struct.unpack(">IIB", epb[28:37])
    assert (seconds, micros, event) == (1_700_000_000, 123456, 0x02)
    assert epb[40 : 40 + len(CHUNKS[0][1])] == CHUNKS[0][1]


def test_a_classic_pcap_with_a_user_link_type_is_read_too(tmp_path: Path) -> None:
    path = tmp_path / "other.pcap"
    head = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 147)
    body = b"".join(struct.pack("<IIII", int(t), round(t % 1 * 1e6), len(d), len(d)) + d
                    for t, d in CHUNKS)
    path.write_bytes(head + body)
    cap = read_capture(path)
    assert cap.framing is None  # pcap has nowhere to say: --baudrate
    assert [d for _, d in cap.chunks] == [d for _, d in CHUNKS]


@pytest.mark.parametrize(("content", "why"), [
    (b"hello, this is not a capture at all", "not a pcapng or pcap"),
    (b"\x0a\x0d\x0d\x0a\x40\x00\x00\x00\x4d\x3c\x2b\x1a", "truncated or damaged"),
])
def test_a_file_that_is_not_a_capture_is_one_line(tmp_path: Path, content: bytes, why: str
                                                  ) -> None:
    path = tmp_path / "bad.pcapng"
    path.write_bytes(content)
    with pytest.raises(UsageError, match=why):
        read_capture(path)


def test_a_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="cannot read"):
        read_capture(tmp_path / "nothing.pcapng")
