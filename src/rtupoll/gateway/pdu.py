"""What a client's request PDU asks for, whether it is well formed, and replies, pure.

A PDU is ``function, data`` (Modbus TCP and RTU share it; no unit, no CRC). Lengths
come from the one function table (``rtupoll.rtu.functions``); this module adds what a
server checks before it acts (quantities, ranges, byte counts), with the exception
code a Modbus server answers for each mistake.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

from rtupoll.errors import ClientError
from rtupoll.rtu import Table
from rtupoll.rtu.effects import Effect, effect
from rtupoll.rtu.functions import (
    FUNCTIONS,
    MAX_QUANTITY,
    READ_FUNCTIONS,
    TABLES,
    bits,
    data_bytes,
    pack_bits,
    request_length,
    words,
)

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 0x01, 0x02, 0x03
PATH_UNAVAILABLE, TARGET_FAILED = 0x0A, 0x0B


class BadRequest(ClientError):
    """A request a server refuses with an exception ``code`` before it reaches the line."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code, self.reason = code, reason


@dataclass(frozen=True)
class Ask:
    """A request PDU, understood: which table and registers, and whether it writes."""

    pdu: bytes
    function: int
    table: Table | None = None  # None: a function with no table (diagnostics, ids, ...)
    address: int = 0
    count: int = 0
    values: tuple[int, ...] = ()  # written registers (6, 16) or bits (5, 15)

    @property
    def write(self) -> bool:
        """Whether it writes registers or coils (``rtupoll.rtu.effects``)."""
        return effect(self.pdu) is Effect.WRITE

    @property
    def read(self) -> bool:
        return self.function in READ_FUNCTIONS

    def touches(self, table: Table, lo: int, hi: int) -> bool:
        """Whether it reads or writes any of ``table``'s registers lo..hi-1."""
        return self.table is table and self.address < hi and lo < self.address + self.count


def pdu_length(pdu: bytes) -> int | None:
    """The request PDU's length by the function table; None: unknown function, or its
    byte count is missing."""
    n = request_length(b"\x00" + pdu[:10])
    return None if n is None else n - 3


def parse(pdu: bytes) -> Ask:
    """Understand a complete request PDU, or raise ``BadRequest`` with the code to answer."""
    if not pdu:
        raise BadRequest(ILLEGAL_FUNCTION, "empty PDU")
    fc = pdu[0]
    if fc not in FUNCTIONS or fc & 0x80:
        raise BadRequest(ILLEGAL_FUNCTION, f"function {fc} is not a Modbus request rtupoll "
                         "passes on")
    want = pdu_length(pdu)
    if want is None and FUNCTIONS[fc].request.count_at:
        raise BadRequest(ILLEGAL_VALUE, f"{FUNCTIONS[fc].name}: truncated ({len(pdu)} bytes)")
    if want is not None and want != len(pdu):
        raise BadRequest(ILLEGAL_VALUE, f"{FUNCTIONS[fc].name}: {len(pdu)} bytes, the "
                         f"function takes {want}")
    if fc not in TABLES:
        return Ask(pdu, fc)
    address, n = struct.unpack_from(">HH", pdu, 1)
    table = TABLES[fc]
    if fc in (5, 6):
        if fc == 5 and n not in (0x0000, 0xFF00):
            raise BadRequest(ILLEGAL_VALUE, f"coil value 0x{n:04X} is neither ON nor OFF")
        return Ask(pdu, fc, table, address, 1, (int(n == 0xFF00) if fc == 5 else n,))
    if not 1 <= n <= MAX_QUANTITY[fc]:
        raise BadRequest(ILLEGAL_VALUE, f"{FUNCTIONS[fc].name}: quantity {n} is outside "
                         f"1..{MAX_QUANTITY[fc]}")
    if address + n > 0x10000:
        raise BadRequest(ILLEGAL_ADDRESS, f"0x{address:04X} + {n} runs past 0xFFFF")
    if fc in READ_FUNCTIONS:
        return Ask(pdu, fc, table, address, n)
    size = pdu[5]
    if size != data_bytes(1 if fc == 15 else 3, n):
        raise BadRequest(ILLEGAL_VALUE, f"byte count {size} does not fit quantity {n}")
    values = words(pdu[6:]) if fc == 16 else bits(pdu[6:], n)
    return Ask(pdu, fc, table, address, n, values)


def read_reply(function: int, values: Sequence[int]) -> bytes:
    """The normal reply PDU to a read: registers (3, 4) or bits (1, 2) packed LSB first."""
    if function in (3, 4):
        data = b"".join(struct.pack(">H", v & 0xFFFF) for v in values)
    else:
        data = pack_bits(values)
    return bytes((function, len(data))) + data


def write_reply(ask: Ask) -> bytes:
    """The normal reply PDU to a write: an echo (5, 6) or address and quantity (15, 16)."""
    if ask.function in (5, 6):
        return ask.pdu[:5]
    return struct.pack(">BHH", ask.function, ask.address, ask.count)


def exception_pdu(function: int, code: int) -> bytes:
    return bytes((function | 0x80, code))
