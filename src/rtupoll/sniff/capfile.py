"""Capture files: every chunk of bytes the tap delivered, with its arrival time.

The format is **pcapng** (what Wireshark, tshark and tcpdump read) with link type
**250, LINKTYPE_RTAC_SERIAL**: the registered link type for a serial line carrying an
industrial protocol. Each packet is one chunk as the adapter delivered it, so nothing
is lost or re-split: a 12-byte RTAC header (arrival time as big-endian seconds and
microseconds, event type 0x02 DATA_RX_START, control lines 0, footer 0) followed by
the bytes. In Wireshark, *Decode As* RTAC Serial -> Modbus/RTU shows the frames
decoded. The line's settings are kept in the interface block: ``if_speed`` (the baud
rate, bits/s) and ``if_description`` (``rtupoll 9600 8N1 /dev/ttyUSB0``), so
``rtupoll sniff --read`` needs no options.

Reading also accepts classic pcap files and pcapng files from other tools, with link
type 250 or a user link type (147-162: the payload is taken as the raw bytes); the
baud rate then comes from ``--baudrate``.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from rtupoll.errors import UsageError
from rtupoll.rtu.timing import Framing

LINKTYPE_RTAC_SERIAL = 250
USER_LINKTYPES = range(147, 163)  # LINKTYPE_USER0..15
RTAC_HEADER = 12
RTAC_DATA_RX = 0x02
FLUSH_EVERY = 0.25  # seconds of capture time between flushes to disk

_SHB, _IDB, _EPB, _SPB = 0x0A0D0D0A, 1, 6, 3
_BOM = 0x1A2B3C4D


@dataclass
class Capture:
    """A capture read back: the line's settings (when recorded) and the chunks."""

    framing: Framing | None
    port: str = ""
    chunks: list[tuple[float, bytes]] = field(default_factory=list)  # (arrival, bytes)


def _option(code: int, value: bytes) -> bytes:
    pad = -len(value) % 4
    return struct.pack("<HH", code, len(value)) + value + b"\0" * pad


def _block(kind: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", kind, total) + body + struct.pack("<I", total)


def describe_framing(framing: Framing) -> str:
    stop = f"{framing.stopbits:g}"
    return f"{framing.baudrate} {framing.bytesize}{framing.parity}{stop}"


class CaptureWriter:
    """Writes a pcapng capture as chunks arrive; flushed now and then, and on close."""

    def __init__(self, path: Path, framing: Framing, port: str = "") -> None:
        try:
            self.fh: BinaryIO = path.open("wb")
        except OSError as exc:
            raise UsageError(f"cannot write {path}: {exc.strerror}") from None
        self.path = path
        self._flushed = float("-inf")
        opts = _option(4, b"rtupoll sniff") + _option(0, b"")
        shb = struct.pack("<IHHq", _BOM, 1, 0, -1) + opts
        desc = f"rtupoll {describe_framing(framing)} {port}".strip().encode()
        idb_opts = (_option(2, port.encode()) if port else b"") + _option(3, desc) \
            + _option(8, struct.pack("<Q", framing.baudrate)) + _option(0, b"")
        idb = struct.pack("<HHI", LINKTYPE_RTAC_SERIAL, 0, 0) + idb_opts
        self.fh.write(_block(_SHB, shb) + _block(_IDB, idb))
        self.fh.flush()  # a valid (empty) capture from the start

    def write(self, data: bytes, t: float) -> None:
        """One chunk; ``t``: its arrival, seconds since the epoch."""
        micros = round(t * 1_000_000)
        seconds, fraction = divmod(micros, 1_000_000)
        payload = struct.pack(">IIBBH", seconds, fraction, RTAC_DATA_RX, 0, 0) + data
        pad = b"\0" * (-len(payload) % 4)
        body = struct.pack("<IIIII", 0, micros >> 32, micros & 0xFFFFFFFF, len(payload),
                           len(payload)) + payload + pad
        self.fh.write(_block(_EPB, body))
        if t - self._flushed >= FLUSH_EVERY:
            self.fh.flush()
            self._flushed = t

    def close(self) -> None:
        if not self.fh.closed:
            self.fh.close()


def read_capture(path: Path) -> Capture:
    """A pcapng or pcap file -> its chunks (and the line's settings when recorded)."""
    stream = CaptureStream(path)
    chunks = list(stream.chunks())
    return Capture(stream.framing, stream.port, chunks)


class CaptureStream:
    """A capture read as it is iterated: the line's settings at once, then the chunks
    block by block (each ``chunks()`` reads the file again from its start), so a
    capture of any length costs the memory of one block."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.framing: Framing | None = None
        self.port = ""
        with self._open() as fh:
            head = fh.read(24)
        self._pcapng = len(head) >= 4 and struct.unpack("<I", head[:4])[0] == _SHB
        if not self._pcapng and len(head) < 24:
            raise UsageError(f"{path}: not a pcapng or pcap capture")
        next(self.chunks(), None)  # up to the first chunk: the settings come before it

    def _open(self) -> BinaryIO:
        try:
            return self.path.open("rb")
        except OSError as exc:
            raise UsageError(f"cannot read {self.path}: {exc.strerror}") from None

    def chunks(self) -> Iterator[tuple[float, bytes]]:
        """Every chunk, in order: (arrival, bytes)."""
        with self._open() as fh:
            size = os.fstat(fh.fileno()).st_size
            yield from (self._pcapng_chunks(fh, size) if self._pcapng
                        else _pcap(fh, size, self.path))

    def _pcapng_chunks(self, fh: BinaryIO, size: int) -> Iterator[tuple[float, bytes]]:
        links: list[tuple[int, float]] = []  # per interface: link type, seconds per tick
        described = False
        for kind, body, endian in _blocks(fh, size, self.path):
            if kind == _SHB:
                links = []
            elif kind == _IDB:
                link = struct.unpack(endian + "H", body[:2])[0]
                opts = dict(_options(body[8:], endian))
                resol = opts.get(9, b"\x06")[0]
                tick = 2.0 ** -(resol & 0x7F) if resol & 0x80 else 10.0 ** -resol
                links.append((link, tick))
                if not described:
                    described = True
                    self.port = opts.get(2, b"").decode(errors="replace")
                    self.framing = _framing(opts.get(3, b"").decode(errors="replace"),
                                            opts.get(8))
            elif kind == _EPB:
                iface, hi, lo, caplen = struct.unpack(endian + "IIII", body[:16])
                if iface >= len(links):
                    raise UsageError(f"{self.path}: a packet names an interface that was "
                                     "not described")
                link, tick = links[iface]
                yield ((hi << 32) | lo) * tick, _payload(link, body[20 : 20 + caplen],
                                                         self.path)


def _blocks(fh: BinaryIO, size: int, path: Path) -> Iterator[tuple[int, bytes, str]]:
    i, endian = 0, "<"
    while i + 12 <= size:
        head = fh.read(12)
        if len(head) < 12:
            return
        kind = struct.unpack("<I", head[:4])[0]
        if kind == _SHB:
            bom = head[8:12]
            endian = "<" if struct.unpack("<I", bom)[0] == _BOM else ">"
        total = struct.unpack(endian + "I", head[4:8])[0]
        kind = struct.unpack(endian + "I", head[:4])[0]
        if total < 12 or i + total > size:
            raise UsageError(f"{path}: truncated or damaged pcapng block at byte {i}")
        block = head + fh.read(total - 12)
        yield kind, block[8 : total - 4], endian
        i += total


def _options(data: bytes, endian: str) -> Iterator[tuple[int, bytes]]:
    i = 0
    while i + 4 <= len(data):
        code, size = struct.unpack(endian + "HH", data[i : i + 4])
        if code == 0:
            return
        yield code, data[i + 4 : i + 4 + size]
        i += 4 + size + (-size % 4)


def _framing(desc: str, speed: bytes | None) -> Framing | None:
    words = desc.split()
    if len(words) >= 3 and words[0] == "rtupoll" and words[1].isdigit() and len(words[2]) >= 3:
        form = words[2]
        try:
            return Framing(int(words[1]), int(form[0]), form[1], float(form[2:]))
        except ValueError:
            pass
    if speed is not None and len(speed) == 8:
        return Framing(struct.unpack("<Q", speed)[0] or 9600)
    return None


def _payload(link: int, data: bytes, path: Path) -> bytes:
    if link == LINKTYPE_RTAC_SERIAL:
        return data[RTAC_HEADER:]
    if link in USER_LINKTYPES:
        return data
    raise UsageError(f"{path}: link type {link} is not a serial line (expected "
                     f"{LINKTYPE_RTAC_SERIAL} RTAC serial, or a user link type 147-162)")


def _pcap(fh: BinaryIO, size: int, path: Path) -> Iterator[tuple[float, bytes]]:
    header = fh.read(24)
    magic = header[:4]
    formats = {b"\xd4\xc3\xb2\xa1": ("<", 1e-6), b"\xa1\xb2\xc3\xd4": (">", 1e-6),
               b"\x4d\x3c\xb2\xa1": ("<", 1e-9), b"\xa1\xb2\x3c\x4d": (">", 1e-9)}
    if magic not in formats:
        raise UsageError(f"{path}: not a pcapng or pcap capture")
    endian, unit = formats[magic]
    link = struct.unpack(endian + "I", header[20:24])[0] & 0xFFFF
    i = 24
    while i + 16 <= size:
        sec, frac, caplen, _ = struct.unpack(endian + "IIII", fh.read(16))
        data = fh.read(min(caplen, size - i - 16))
        yield sec + frac * unit, _payload(link, data, path)
        i += 16 + caplen
