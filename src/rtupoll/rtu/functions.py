"""Modbus RTU on the wire: tables, CRC, frames, exception names and timing.

Pure functions only. The bus module sends frames through pymodbus; the simulator,
``rtupoll decode`` and ``--dry-run`` build and parse them here, so there is one
definition of what a frame is.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence

from rtupoll.rtu.crc import with_crc


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

def exception_name(code: int) -> str:
    return EXCEPTION_NAMES.get(code, "UNKNOWN EXCEPTION")


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


def read_frame_sizes(count: int, *, coils: bool = False) -> tuple[int, int]:
    """Request and normal response sizes (bytes, CRC included) of one read."""
    data = (count + 7) // 8 if coils else 2 * count
    return 8, 5 + data
