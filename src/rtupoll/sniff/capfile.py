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

import contextlib
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from rtupoll.errors import UsageError
from rtupoll.rtu.timing import Framing

LINKTYPE_RTAC_SERIAL = 250
USER_LINKTYPES = range(147, 163)  # LINKTYPE_USER0..15
RTAC_HEADER = 12
RTAC_DATA_TX, RTAC_DATA_RX = 0x01, 0x02  # event types: DATA_TX_START, DATA_RX_START
FLUSH_EVERY = 0.25  # seconds of capture time between flushes to disk

_SHB, _IDB, _EPB, _SPB = 0x0A0D0D0A, 1, 6, 3
_BOM = 0x1A2B3C4D


@dataclass
class Capture:
    """A capture read back: the line's settings (when recorded) and the chunks."""

    framing: Framing | None
    port: str = ""
    chunks: list[tuple[float, bytes]] = field(default_factory=list)  # (arrival, bytes)
    stopped: str = ""  # where a damaged or truncated file stopped being read, and why


class _Damaged(Exception):
    """A block that cannot be read: the capture is read up to it (at byte ``at``)."""

    def __init__(self, why: str, at: int | None = None) -> None:
        super().__init__(why)
        self.at = at


def _option(code: int, value: bytes) -> bytes:
    pad = -len(value) % 4
    return struct.pack("<HH", code, len(value)) + value + b"\0" * pad


def _block(kind: int, body: bytes) -> bytes:
    total = 12 + len(body)
    return struct.pack("<II", kind, total) + body + struct.pack("<I", total)


def _interface(framing: Framing, port: str) -> bytes:
    """An interface block: the line's port, settings and speed."""
    desc = f"rtupoll {describe_framing(framing)} {port}".strip().encode()
    opts = (_option(2, port.encode()) if port else b"") + _option(3, desc) \
        + _option(8, struct.pack("<Q", framing.baudrate)) + _option(0, b"")
    return _block(_IDB, struct.pack("<HHI", LINKTYPE_RTAC_SERIAL, 0, 0) + opts)


def describe_framing(framing: Framing) -> str:
    stop = f"{framing.stopbits:g}"
    return f"{framing.baudrate} {framing.bytesize}{framing.parity}{stop}"


class CaptureWriter:
    """Writes a pcapng capture as chunks arrive; flushed now and then, and on close."""

    def __init__(self, path: Path, framing: Framing, port: str = "", *,
                 say: Callable[[str], None] | None = None,
                 application: str = "rtupoll sniff") -> None:
        self.path, self.say = path, say
        self.error = ""  # why capturing stopped (a full disk): listening goes on
        self.packets = 0
        self._flushed = float("-inf")
        self._good = 0  # bytes of whole blocks known on disk
        self._ends: list[int] = []  # block ends written since
        self._size = 0
        opts = _option(4, application.encode()) + _option(0, b"")
        shb = struct.pack("<IHHq", _BOM, 1, 0, -1) + opts
        head = _block(_SHB, shb) + _interface(framing, port)
        self.interfaces = 1
        try:
            self.fh: BinaryIO = path.open("wb")
            self.fh.write(head)
            self.fh.flush()  # a valid (empty) capture from the start
        except OSError as exc:
            raise UsageError(f"cannot write {path}: {exc.strerror or exc}") from None
        self._good = self._size = len(head)

    def add_interface(self, framing: Framing, port: str) -> int:
        """Another line (one capture of several buses): its interface id for ``write``."""
        self._put(_interface(framing, port))
        self.interfaces += 1
        return self.interfaces - 1

    def write(self, data: bytes, t: float, *, interface: int = 0, sent: bool = False) -> None:
        """One chunk; ``t``: its arrival (or for ``sent`` bytes, the time they went out),
        seconds since the epoch. A write that fails (a full disk) ends the capture, with
        whole blocks only, and says so once."""
        micros = round(t * 1_000_000)
        seconds, fraction = divmod(micros, 1_000_000)
        event = RTAC_DATA_TX if sent else RTAC_DATA_RX
        payload = struct.pack(">IIBBH", seconds, fraction, event, 0, 0) + data
        pad = b"\0" * (-len(payload) % 4)
        body = struct.pack("<IIIII", interface, micros >> 32, micros & 0xFFFFFFFF,
                           len(payload), len(payload)) + payload + pad
        if self._put(_block(_EPB, body)):
            self.packets += 1
            if t - self._flushed >= FLUSH_EVERY:
                try:
                    self._flush()
                except OSError as exc:
                    self._fail(exc)
                self._flushed = t

    def _put(self, block: bytes) -> bool:
        if self.error:
            return False
        try:
            self.fh.write(block)
        except OSError as exc:
            self._fail(exc)
            return False
        self._size += len(block)
        self._ends.append(self._size)
        return True

    def _flush(self) -> None:
        self.fh.flush()
        self._good, self._ends = self._size, []

    def _fail(self, exc: OSError) -> None:
        """Stop capturing: close, cut the file back to its last whole block, say why."""
        with contextlib.suppress(OSError):
            self.fh.close()
        kept = self._good
        with contextlib.suppress(OSError):
            on_disk = self.path.stat().st_size
            kept = max([self._good, *(e for e in self._ends if e <= on_disk)])
            os.truncate(self.path, kept)
        whole = self.packets - sum(1 for e in self._ends if e > kept)
        self.error = (f"capture to {self.path} stopped: {exc.strerror or exc}; its first "
                      f"{whole} packets are kept whole, listening goes on")
        if self.say is not None:
            self.say(self.error)

    def close(self) -> None:
        if self.fh.closed:
            return
        try:
            self._flush()
            self.fh.close()
        except OSError as exc:
            self._fail(exc)


def read_capture(path: Path) -> Capture:
    """A pcapng or pcap file -> its chunks (and the line's settings when recorded)."""
    stream = CaptureStream(path)
    chunks = list(stream.chunks())
    return Capture(stream.framing, stream.port, chunks, stream.stopped)


class CaptureStream:
    """A capture read as it is iterated: the line's settings at once, then the chunks
    block by block (each ``chunks()`` reads the file again from its start), so a
    capture of any length costs the memory of one block.

    A damaged or truncated block (a full disk, a power loss, a kill -9) ends the reading
    there, as Wireshark does: every chunk before it is delivered, and ``stopped`` then
    says where and why. A file whose very first block is damaged is refused."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.framing: Framing | None = None
        self.port = ""
        self.stopped = ""  # set when an iteration of ``chunks()`` met damage
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
        """Every chunk up to the end or the first damage, in order: (arrival, bytes)."""
        self.stopped = ""
        with self._open() as fh:
            size = os.fstat(fh.fileno()).st_size
            yield from (self._pcapng_chunks(fh, size) if self._pcapng
                        else self._pcap_chunks(fh, size))

    def _pcapng_chunks(self, fh: BinaryIO, size: int) -> Iterator[tuple[float, bytes]]:
        links: list[tuple[int, float]] = []  # per interface: link type, seconds per tick
        count = 0
        try:
            for at, kind, body, endian in _blocks(fh, size):
                try:
                    chunk = self._block(links, kind, body, endian)
                except _Damaged as exc:
                    raise _Damaged(str(exc), at) from None
                if chunk is not None:
                    count += 1
                    yield chunk
        except _Damaged as exc:
            if not exc.at:  # not even its section header: nothing to read
                raise UsageError(f"{self.path}: {exc} at byte 0: not a readable capture"
                                 ) from None
            self.stopped = f"{exc} at byte {exc.at}: read the {count} packets before it"

    def _block(self, links: list[tuple[int, float]], kind: int, body: bytes,
               endian: str) -> tuple[float, bytes] | None:
        if kind == _SHB:
            links.clear()
        elif kind == _IDB:
            if len(body) < 8:
                raise _Damaged(f"an interface block of {len(body) + 12} bytes (at least 20)")
            link = struct.unpack(endian + "H", body[:2])[0]
            opts = dict(_options(body[8:], endian))
            resol = (opts.get(9) or b"\x06")[0]
            tick = 2.0 ** -(resol & 0x7F) if resol & 0x80 else 10.0 ** -resol
            links.append((link, tick))
            if len(links) == 1:
                self.port = opts.get(2, b"").decode(errors="replace")
                self.framing = _framing(opts.get(3, b"").decode(errors="replace"),
                                        opts.get(8))
        elif kind == _EPB:
            if len(body) < 20:
                raise _Damaged(f"an enhanced packet block of {len(body) + 12} bytes "
                               f"(at least 32)")
            iface, hi, lo, caplen = struct.unpack(endian + "IIII", body[:16])
            if 20 + caplen > len(body):
                raise _Damaged(f"a packet of {caplen} bytes in a block of {len(body) + 12}")
            if iface >= len(links):
                raise _Damaged("a packet names an interface that was not described")
            link, tick = links[iface]
            return ((hi << 32) | lo) * tick, _payload(link, body[20 : 20 + caplen], self.path)
        return None

    def _pcap_chunks(self, fh: BinaryIO, size: int) -> Iterator[tuple[float, bytes]]:
        header = fh.read(24)
        formats = {b"\xd4\xc3\xb2\xa1": ("<", 1e-6), b"\xa1\xb2\xc3\xd4": (">", 1e-6),
                   b"\x4d\x3c\xb2\xa1": ("<", 1e-9), b"\xa1\xb2\x3c\x4d": (">", 1e-9)}
        if header[:4] not in formats:
            raise UsageError(f"{self.path}: not a pcapng or pcap capture")
        endian, unit = formats[header[:4]]
        link = struct.unpack(endian + "I", header[20:24])[0] & 0xFFFF
        i, count = 24, 0
        while i < size:
            if i + 16 > size:
                self.stopped = f"a truncated record header at byte {i}"
                break
            sec, frac, caplen, _ = struct.unpack(endian + "IIII", fh.read(16))
            if i + 16 + caplen > size:
                self.stopped = (f"a truncated record ({caplen} bytes, {size - i - 16} left) "
                                f"at byte {i}")
                break
            yield sec + frac * unit, _payload(link, fh.read(caplen), self.path)
            count += 1
            i += 16 + caplen
        if self.stopped:
            self.stopped += f": read the {count} packets before it"


def _blocks(fh: BinaryIO, size: int) -> Iterator[tuple[int, int, bytes, str]]:
    """(offset, kind, body, byte order) of each block, read one at a time; ``_Damaged``
    at one that is cut short or says a length it cannot have."""
    i, endian = 0, "<"
    while i < size:
        head = fh.read(12) if i + 12 <= size else b""
        if len(head) < 12:
            raise _Damaged(f"a truncated block ({size - i} bytes)", i)
        kind = struct.unpack("<I", head[:4])[0]
        if kind == _SHB:
            endian = "<" if struct.unpack("<I", head[8:12])[0] == _BOM else ">"
        total = struct.unpack(endian + "I", head[4:8])[0]
        kind = struct.unpack(endian + "I", head[:4])[0]
        if total < 12 or total % 4 or i + total > size:
            raise _Damaged(f"a truncated or damaged block (it says {total} bytes, "
                           f"{size - i} are left)", i)
        block = head + fh.read(total - 12)
        yield i, kind, block[8 : total - 4], endian
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
