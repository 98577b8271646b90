"""rtupoll's own frames while it works (``--traffic``, ``--capture``): what ``sniff``
shows of another master, for the master rtupoll is.

Each request as it goes out, and what comes back as whole frames (by their length and
CRC), as log lines on stderr: time, direction, port, the bytes in hex and what they
are (``rtu.capture``'s decoding); bytes that make no frame are shown when the next
request goes out or the command ends. ``--capture FILE`` writes the same bytes to a
pcapng file (the format ``sniff --capture`` writes, requests marked as sent), one
interface for each bus.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import TextIO

from rtupoll.model.record import iso_time
from rtupoll.rtu.capture import Frame, decode_frame
from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.functions import MAX_FRAME, reply_length
from rtupoll.rtu.timing import Framing
from rtupoll.sniff.capfile import CaptureWriter
from rtupoll.sniff.lines import clock


class Traffic:
    """The sink for ``rtupoll.io.taps``: log lines (``fmt`` text or json, or None) and a
    capture file (or None)."""

    def __init__(self, fmt: str | None, capture: Path | None, *,
                 out: TextIO | None = None) -> None:
        self.fmt, self.capture_path = fmt, capture
        self.out = out or sys.stderr
        self.capture: CaptureWriter | None = None
        self._interface: dict[str, int] = {}
        self._heard: dict[str, bytearray] = {}  # per port: received bytes not yet shown
        self._asked: dict[str, Frame] = {}  # per port: the last request, for decoding

    def __call__(self, port: str, framing: Framing, sent: bool, data: bytes) -> None:
        now = time.time()
        if self.capture_path is not None:
            self._capture(port, framing, sent, data, now)
        if self.fmt is None:
            return
        heard = self._heard.setdefault(port, bytearray())
        if sent:
            self._leftover(port, heard, now)
            frame = decode_frame(data, "request")
            self._asked[port] = frame
            self._line(now, port, "tx", frame)
            return
        heard += data
        while len(heard) >= 5:
            size = reply_length(bytes(heard[:MAX_FRAME]))
            if size is None or size > len(heard):
                break  # more to come (or the rest is shown as it is, later)
            if not crc_ok(bytes(heard[:size])):
                break
            frame = decode_frame(bytes(heard[:size]), None, self._asked.get(port))
            del heard[:size]
            self._line(now, port, "rx", frame)

    def close(self) -> None:
        """The command ends: what was heard and made no frame is shown; the file closed."""
        now = time.time()
        for port, heard in self._heard.items():
            self._leftover(port, heard, now)
        if self.capture is not None:
            self.capture.close()

    def _leftover(self, port: str, heard: bytearray, now: float) -> None:
        if heard and self.fmt is not None:
            self._line(now, port, "rx", decode_frame(bytes(heard), None, self._asked.get(port)))
        heard.clear()

    def _capture(self, port: str, framing: Framing, sent: bool, data: bytes,
                 now: float) -> None:
        if self.capture is None:
            assert self.capture_path is not None
            self.capture = CaptureWriter(self.capture_path, framing, port,
                                         say=self._say, application="rtupoll")
            self._interface[port] = 0
        elif port not in self._interface:
            self._interface[port] = self.capture.add_interface(framing, port)
        self.capture.write(data, now, interface=self._interface[port], sent=sent)

    def _say(self, message: str) -> None:
        print(f"rtupoll: {message}", file=self.out, flush=True)

    def _line(self, now: float, port: str, direction: str, frame: Frame) -> None:
        what = describe(frame)
        if self.fmt == "json":
            rec = {"time": iso_time(now), "port": port, "direction": direction,
                   "hex": frame.raw.hex(" ").upper(), "crc_ok": frame.crc_ok,
                   "unit": frame.unit, "function": frame.function, "decoded": what}
            print(json.dumps(rec, ensure_ascii=False), file=self.out, flush=True)
            return
        arrow = "->" if direction == "tx" else "<-"
        print(f"{clock(now)} {arrow} {port} {frame.raw.hex(' ').upper()}  {what}",
              file=self.out, flush=True)


def describe(frame: Frame) -> str:
    """A frame in words, as short as a log line wants it."""
    if frame.kind == "noise" or frame.unit is None:
        return "; ".join(frame.notes) or "noise"
    parts = [f"unit {frame.unit}", frame.function_name]
    if frame.table is not None and frame.start is not None:
        last = frame.start + (frame.count or 1) - 1
        parts.append(f"{frame.table.value} {frame.start}" + (f"..{last}" if last > frame.start
                                                             else ""))
    if frame.values and frame.kind == "response":
        shown = ", ".join(map(str, frame.values[:8]))
        parts.append(f"= {shown}" + (" ..." if len(frame.values) > 8 else ""))
    if not frame.crc_ok:
        parts.append("CRC ERROR")
    notes = [n for n in frame.notes if not n.startswith("function 0x")]
    return " ".join(parts) + (f" ({'; '.join(notes)})" if notes else "")
