"""What Home Assistant and Telegraf would show for registers, and a device holding them.

Written from the two tools' documented semantics, not from rtupoll's codec, so that an
import test compares rtupoll against them and not against itself:

- Home Assistant's modbus sensor: the registers' bytes big-endian, ``swap: byte`` swaps
  the bytes of each register, ``swap: word`` reverses the registers (``word_byte``
  both); then ``struct`` by ``data_type``; ``value * scale + offset``, rounded to
  ``precision``. A string drops its NUL bytes.
- Telegraf's modbus input: ``byte_order`` names the order in which the value's bytes
  (A = most significant) stand on the wire; four letters widen to eight for 64-bit
  values and shrink to two for 16-bit ones; ``scale`` multiplies (a scale of 0 is none).

``Responder`` is a Modbus RTU device behind an RTU-over-TCP gateway: the registers
given, answers to FC 1-4, silence for other units.
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Sequence
from typing import Any

HA_FORMATS = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "int64": "q",
              "uint64": "Q", "float32": "f", "float64": "d"}
HA_LEGACY = {("int", 1): "int16", ("int", 2): "int32", ("int", 4): "int64",
             ("uint", 1): "uint16", ("uint", 2): "uint32", ("uint", 4): "uint64",
             ("float", 2): "float32", ("float", 4): "float64"}


def _swap_bytes(raw: bytes) -> bytes:
    return b"".join(raw[i + 1:i + 2] + raw[i:i + 1] for i in range(0, len(raw), 2))


def _regs(raw: bytes) -> list[int]:
    return [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]


def ha_encode(raw_value: int | float | str, data_type: str, swap: str = "none",
              count: int = 1) -> list[int]:
    """The registers from which Home Assistant reads ``raw_value`` (before scale)."""
    if data_type == "string":
        data = str(raw_value).encode().ljust(2 * count, b"\0")
    else:
        data = struct.pack(">" + HA_FORMATS[data_type], raw_value)
    if swap in ("byte", "word_byte"):
        data = _swap_bytes(data)
    regs = _regs(data)
    if swap in ("word", "word_byte"):
        regs.reverse()
    return regs


def ha_shows(regs: Sequence[int], conf: dict[str, Any]) -> Any:
    """What Home Assistant shows for a sensor ``conf`` reading ``regs``."""
    data_type = conf.get("data_type", "int16")
    data_type = HA_LEGACY.get((data_type, conf.get("count", 1)), data_type)
    swap = "word" if conf.get("reverse_order") else conf.get("swap", "none")
    regs = list(regs)
    if swap in ("word", "word_byte"):
        regs.reverse()
    data = b"".join(r.to_bytes(2, "big") for r in regs)
    if swap in ("byte", "word_byte"):
        data = _swap_bytes(data)
    if data_type == "string":
        return data.replace(b"\0", b"").decode()
    value = struct.unpack(">" + HA_FORMATS[data_type], data)[0]
    value = value * conf.get("scale", 1) + conf.get("offset", 0)
    precision = conf.get("precision", 0)
    return round(value, precision) if precision else round(value)


TG_WIDE = {"ABCD": "ABCDEFGH", "DCBA": "HGFEDCBA", "BADC": "BADCFEHG", "CDAB": "GHEFCDAB"}
TG_FORMATS = {"INT16": "h", "UINT16": "H", "INT32": "i", "UINT32": "I", "INT64": "q",
              "UINT64": "Q", "FLOAT32": "f", "FLOAT64": "d", "FLOAT32-IEEE": "f",
              "FLOAT64-IEEE": "d"}


def tg_order(order: str, size: int) -> str:
    order = order.upper()
    if size == 8 and len(order) == 4:
        return TG_WIDE[order]
    if size == 2:
        return order[:2] if len(order) == 2 else ("AB" if order in ("ABCD", "CDAB") else "BA")
    return order


def tg_encode(value: int | float, fmt: str, order: str) -> list[int]:
    """The registers from which Telegraf reads ``value`` with ``byte_order`` ``order``."""
    be = struct.pack(">" + fmt, value)
    letters = tg_order(order, len(be))
    return _regs(bytes(be[ord(c) - ord("A")] for c in letters))


def tg_decode(regs: Sequence[int], fmt: str, order: str) -> int | float:
    wire = b"".join(r.to_bytes(2, "big") for r in regs)
    letters = tg_order(order, len(wire))
    be = bytearray(len(wire))
    for pos, c in enumerate(letters):
        be[ord(c) - ord("A")] = wire[pos]
    return float(struct.unpack(">" + fmt, bytes(be))[0])


def crc16(data: bytes) -> bytes:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


class Responder:
    """Units with four tables each, behind an RTU-over-TCP socket on 127.0.0.1."""

    def __init__(self) -> None:
        # unit -> function code (1 coil, 2 discrete, 3 holding, 4 input) -> address -> value
        self.units: dict[int, dict[int, dict[int, int]]] = {}
        self._socks: list[socket.socket] = []
        self._stop = False

    def port(self) -> int:
        """A new listening port on the same devices (one per bus: a site file gives each
        bus a port of its own)."""
        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        self._socks.append(sock)
        threading.Thread(target=self._serve, args=(sock,), daemon=True).start()
        return int(sock.getsockname()[1])

    def set(self, unit: int, fc: int, address: int, values: Sequence[int]) -> None:
        table = self.units.setdefault(unit, {}).setdefault(fc, {})
        for k, v in enumerate(values):
            table[address + k] = v

    def __enter__(self) -> Responder:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop = True
        for sock in self._socks:
            sock.close()

    def _serve(self, sock: socket.socket) -> None:
        while not self._stop:
            try:
                conn, _ = sock.accept()
            except OSError:
                return
            threading.Thread(target=self._talk, args=(conn,), daemon=True).start()

    def _talk(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            while True:
                try:
                    chunk = conn.recv(256)
                except OSError:
                    return
                if not chunk:
                    return
                buf += chunk
                while len(buf) >= 8:
                    frame, buf = buf[:8], buf[8:]
                    reply = self._answer(frame)
                    if reply:
                        conn.sendall(reply + crc16(reply))

    def _answer(self, frame: bytes) -> bytes | None:
        if crc16(frame[:6]) != frame[6:]:
            return None
        unit, fc, address, count = frame[0], frame[1], *struct.unpack(">HH", frame[2:6])
        tables = self.units.get(unit)
        if tables is None:
            return None
        table = tables.get(fc, {})
        wanted = range(address, address + count)
        if fc not in (1, 2, 3, 4) or any(a not in table for a in wanted):
            return bytes([unit, fc | 0x80, 2])
        if fc in (3, 4):
            body = b"".join(table[a].to_bytes(2, "big") for a in wanted)
        else:
            bits = sum((table[a] & 1) << k for k, a in enumerate(wanted))
            body = bits.to_bytes((count + 7) // 8, "little")
        return bytes([unit, fc, len(body)]) + body
