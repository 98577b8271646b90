"""Modbus RTU on the wire: tables, CRC, frames, exception names and timing.

Pure functions only. The bus module sends frames through pymodbus; the simulator,
``rtupoll decode`` and ``--dry-run`` build and parse them here, so there is one
definition of what a frame is.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence
from dataclasses import dataclass


class Table(str, enum.Enum):
    """The four Modbus data tables."""

    COIL = "coil"
    DISCRETE = "discrete"
    INPUT = "input"
    HOLDING = "holding"

    @property
    def read_function(self) -> int:
        return {"coil": 1, "discrete": 2, "input": 4, "holding": 3}[self.value]

    @property
    def is_register(self) -> bool:
        return self in (Table.INPUT, Table.HOLDING)

    @property
    def modicon_base(self) -> int:
        """The Modicon reference prefix: 0xxxx coils, 1xxxx, 3xxxx inputs, 4xxxx holding."""
        return {"coil": 0, "discrete": 10000, "input": 30000, "holding": 40000}[self.value]


EXCEPTION_NAMES: dict[int, str] = {
    1: "ILLEGAL FUNCTION",
    2: "ILLEGAL DATA ADDRESS",
    3: "ILLEGAL DATA VALUE",
    4: "SERVER DEVICE FAILURE",
    5: "ACKNOWLEDGE",
    6: "SERVER DEVICE BUSY",
    7: "NEGATIVE ACKNOWLEDGE",
    8: "MEMORY PARITY ERROR",
    10: "GATEWAY PATH UNAVAILABLE",
    11: "GATEWAY TARGET DEVICE FAILED TO RESPOND",
}

FUNCTION_NAMES: dict[int, str] = {
    1: "read coils",
    2: "read discrete inputs",
    3: "read holding registers",
    4: "read input registers",
    5: "write single coil",
    6: "write single register",
    15: "write multiple coils",
    16: "write multiple registers",
}

def parse_int(text: str) -> int:
    """Decimal, 0x hex or a trailing h (``254``, ``0xFE``, ``FEh``), as manuals write them."""
    t = text.strip().lower()
    if t.endswith("h") and len(t) > 1:
        return int(t[:-1], 16)
    return int(t, 0)


def parse_unit(text: str) -> int:
    """A unit (slave) address 0..255; ValueError says what is wrong, in a user's words."""
    try:
        unit = parse_int(text)
    except ValueError:
        raise ValueError(f"{text!r} is not an address (0-255, decimal or 0x..)") from None
    if not 0 <= unit <= 255:
        raise ValueError(f"address {unit} is outside 0..255")
    return unit


def exception_name(code: int) -> str:
    return EXCEPTION_NAMES.get(code, "UNKNOWN EXCEPTION")


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """Modbus CRC-16 (poly 0xA001 reflected, init 0xFFFF). Sent low byte first."""
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ byte) & 0xFF]
    return crc


def with_crc(body: bytes) -> bytes:
    """Append the CRC, low byte first, as it goes on the wire."""
    return body + struct.pack("<H", crc16(body))


def crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and crc16(frame[:-2]) == struct.unpack("<H", frame[-2:])[0]


def read_request(unit: int, table: Table, address: int, count: int) -> bytes:
    return with_crc(struct.pack(">BBHH", unit, table.read_function, address, count))


def write_single_request(unit: int, address: int, value: int) -> bytes:
    return with_crc(struct.pack(">BBHH", unit, 6, address, value))


def write_coil_request(unit: int, address: int, on: bool) -> bytes:
    return with_crc(struct.pack(">BBHH", unit, 5, address, 0xFF00 if on else 0x0000))


def write_multiple_request(unit: int, address: int, values: Sequence[int]) -> bytes:
    body = struct.pack(">BBHHB", unit, 16, address, len(values), 2 * len(values))
    return with_crc(body + b"".join(struct.pack(">H", v) for v in values))


def read_response(unit: int, function: int, words: Sequence[int]) -> bytes:
    data = b"".join(struct.pack(">H", w) for w in words)
    return with_crc(struct.pack(">BBB", unit, function, len(data)) + data)


def exception_response(unit: int, function: int, code: int) -> bytes:
    return with_crc(struct.pack(">BBB", unit, function | 0x80, code))


@dataclass(frozen=True)
class Framing:
    """Serial character framing, for timing: 1 start bit + data + parity + stop bits."""

    baudrate: int
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1

    @property
    def bits_per_char(self) -> float:
        return 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits

    @property
    def char_time(self) -> float:
        return self.bits_per_char / self.baudrate

    @property
    def silence(self) -> float:
        """Inter-frame silence t3.5; the spec fixes it at 1.75 ms above 19200 baud."""
        return 0.00175 if self.baudrate > 19200 else 3.5 * self.char_time

    def wire_time(self, nbytes: int) -> float:
        return nbytes * self.char_time


def read_frame_sizes(count: int, *, coils: bool = False) -> tuple[int, int]:
    """Request and normal response sizes (bytes, CRC included) of one read."""
    data = (count + 7) // 8 if coils else 2 * count
    return 8, 5 + data


def transaction_wire_time(framing: Framing, request: int, response: int) -> float:
    """The least time one transaction holds the bus: both frames plus two silences."""
    return framing.wire_time(request + response) + 2 * framing.silence
