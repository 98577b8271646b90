"""What a client's request PDU asks for, whether it is well formed, and replies, pure.

A PDU is ``function, data`` (Modbus TCP and RTU share it; no unit, no CRC). Lengths
come from the one function table (``rtupoll.rtu.functions``); this module adds what a
server checks before it acts (quantities, ranges, byte counts), with the exception
code a Modbus server answers for each mistake.
"""

from __future__ import annotations

from dataclasses import dataclass

from rtupoll.errors import ClientError
from rtupoll.rtu import Table
from rtupoll.rtu.effects import Effect, effect
from rtupoll.rtu.functions import READ_FUNCTIONS, request_length
from rtupoll.rtu.messages import (
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    Malformed,
    OtherRequest,
    ReadRequest,
    parse_request,
)

__all__ = ["ILLEGAL_ADDRESS", "ILLEGAL_FUNCTION", "ILLEGAL_VALUE", "PATH_UNAVAILABLE",
           "TARGET_FAILED", "Ask", "BadRequest", "parse", "pdu_length"]
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
    """Understand a complete request PDU, or raise ``BadRequest`` with the code to answer
    (the checks are ``rtupoll.rtu.messages.parse_request``'s)."""
    try:
        msg = parse_request(pdu, unit=0)
    except Malformed as exc:
        raise BadRequest(exc.code or ILLEGAL_VALUE, exc.reason) from None
    if isinstance(msg, OtherRequest):
        return Ask(pdu, msg.function)
    if isinstance(msg, ReadRequest):
        return Ask(pdu, msg.function, msg.table, msg.address, msg.count)
    return Ask(pdu, msg.function, msg.table, msg.address, msg.count, msg.values)
