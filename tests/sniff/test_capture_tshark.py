"""The capture format read by an independent reader: tshark (Wireshark's dissectors).

``rtupoll sniff --capture`` writes pcapng with link type 250 (RTAC serial), and
tests/sniff/test_capfile.py reads it back with rtupoll's own reader: a bug both share
(a wrong block length, a timestamp in the wrong unit, a header off by a byte) would
pass there. Here tshark reads what ``CaptureWriter`` wrote: every chunk's bytes and
arrival time, the interface's name and description, and, decoded as Modbus RTU (the
documented *Decode As* RTAC Serial -> Modbus/RTU), every frame's unit, function,
registers and CRC.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest, WriteSingle
from rtupoll.sniff.capfile import CaptureWriter

TSHARK = shutil.which("tshark")
T0 = 1_700_000_000.123456  # an arrival time with every microsecond digit used


def tshark(capture: Path, *fields: str, decode: bool = False) -> list[list[str]]:
    """tshark's fields of every packet in ``capture``: one row per packet."""
    assert TSHARK is not None, "tshark is not installed (scripts/setup --test installs it)"
    args = [TSHARK, "-r", str(capture), "-T", "fields", "-E", "separator=\t",
            "-E", "occurrence=a", "-E", "aggregator=,"]
    if decode:
        args += ["-d", "rtacser.data,mbrtu", "-o", "mbrtu.crc_verification:TRUE"]
    for f in fields:
        args += ["-e", f]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return [line.split("\t") for line in proc.stdout.splitlines()]


def write(path: Path, chunks: list[tuple[float, bytes]], framing: Framing,
          port: str = "/dev/ttyUSB0") -> None:
    writer = CaptureWriter(path, framing, port)
    for t, data in chunks:
        writer.write(data, t)
    writer.close()


def test_tshark_reads_every_chunk_with_its_arrival_time_and_the_interface(
        tmp_path: Path) -> None:
    """Chunks as an adapter delivers them: a frame split in two, lengths 1 to 255 (every
    padding to 4 bytes), an all-0xFF chunk; none is lost, re-split or shifted."""
    request = ReadRequest(3, 3, 0x10, 2).frame()
    chunks = [(T0, request[:3]), (T0 + 0.000_997, request[3:]), (T0 + 1.5, b"\xff" * 7)]
    chunks += [(T0 + 2 + i / 1000, bytes((i + k) & 0xFF for k in range(i)))
               for i in (1, 2, 3, 4, 5, 255)]
    capture = tmp_path / "line.pcapng"
    write(capture, chunks, Framing(19200, parity="E"))
    rows = tshark(capture, "frame.time_epoch", "rtacser.timestamp", "rtacser.eventtype",
                  "data.data", "frame.interface_name", "frame.interface_description")
    assert len(rows) == len(chunks)
    for (t, data), (epoch, stamp, event, payload, name, description) in zip(
            chunks, rows, strict=True):
        micros = round(t * 1_000_000)
        assert epoch == stamp == f"{micros // 1_000_000}.{micros % 1_000_000:06d}000"
        assert int(event, 16) == 0x02  # DATA_RX_START
        assert bytes.fromhex(payload.replace(":", "")) == data
        assert name == "/dev/ttyUSB0"
        assert description == "rtupoll 19200 8E1 /dev/ttyUSB0"


def test_tshark_decodes_the_frames_as_modbus_rtu(tmp_path: Path) -> None:
    """One frame a chunk: a read and its reply, an exception, a write echo, and a reply
    whose CRC is broken, which tshark must call bad where rtupoll calls it garbled."""
    ok = ReadReply(3, 3, (0x1234, 0xABCD)).frame()
    frames = [ReadRequest(3, 3, 0x10, 2).frame(), ok,
              ExceptionReply(7, 4, 2).frame(), WriteSingle(9, 6, 0x9C41, 12).frame(),
              ok[:-1] + bytes((ok[-1] ^ 0xFF,))]
    capture = tmp_path / "frames.pcapng"
    write(capture, [(T0 + i * 0.05, f) for i, f in enumerate(frames)], Framing(9600))
    rows = tshark(capture, "mbrtu.unit_id", "modbus.func_code", "mbrtu.crc16.status",
                  "modbus.reference_num", "modbus.word_cnt", "modbus.regval_uint16",
                  "modbus.exception_code", decode=True)
    good, bad = "1", "0"  # Wireshark's checksum status: PROTO_CHECKSUM_E_GOOD / _BAD
    assert [r[:3] for r in rows] == [["3", "3", good], ["3", "3", good], ["7", "4", good],
                                     ["9", "6", good], ["3", "3", bad]]
    assert rows[0][3:5] == ["16", "2"]  # reference 0x0010, two registers
    assert rows[1][5] == "4660,43981"  # 0x1234, 0xABCD
    assert rows[2][6] == "2"  # ILLEGAL DATA ADDRESS


def test_an_empty_capture_is_a_valid_file(tmp_path: Path) -> None:
    """What ``rtupoll sniff --capture`` leaves when nothing was heard (or it was killed
    before the first byte): a file tshark reads, with no packets."""
    capture = tmp_path / "quiet.pcapng"
    CaptureWriter(capture, Framing(9600)).close()
    assert tshark(capture, "frame.number") == []
    assert TSHARK is not None
    info = subprocess.run([str(Path(TSHARK).with_name("capinfos")), "-E", "-c", str(capture)],
                          capture_output=True, text=True, timeout=60)
    assert info.returncode == 0, info.stderr
    assert "RTAC serial-line" in info.stdout and "Number of packets:   0" in info.stdout
