"""A client's request PDU, understood or refused, pure.

A PDU is ``function, data`` (Modbus TCP and RTU share it; no unit, no CRC). It is
parsed by the one strict request parser (``rtupoll.rtu.messages.parse_request``: the
quantities, ranges and byte counts a server checks before it acts, with the exception
code a Modbus server answers for each mistake); ``Ask`` holds the message and the PDU
as it came, and replies are the reply messages' own ``pdu()``.
"""

from __future__ import annotations

from dataclasses import dataclass

from rtupoll.errors import ClientError
from rtupoll.rtu import Table
from rtupoll.rtu.effects import Effect, effect
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.functions import request_length
from rtupoll.rtu.messages import (
    Malformed,
    ReadRequest,
    Request,
    TableRequest,
    parse_request,
)

__all__ = ["Ask", "BadRequest", "parse", "pdu_length"]


class BadRequest(ClientError):
    """A request a server refuses with an exception ``code`` before it reaches the line."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code, self.reason = code, reason


@dataclass(frozen=True, slots=True)
class Ask:
    """A client's request: its message (``rtu.messages``) and the PDU it came as, which
    goes to the line as it is."""

    message: Request
    pdu: bytes

    @property
    def function(self) -> int:
        return self.message.function

    @property
    def table(self) -> Table | None:
        """None: a function with no table (diagnostics, ids, ...)."""
        m = self.message
        return m.table if isinstance(m, TableRequest) else None

    @property
    def address(self) -> int:
        m = self.message
        return m.address if isinstance(m, TableRequest) else 0

    @property
    def count(self) -> int:
        m = self.message
        return m.count if isinstance(m, TableRequest) else 0

    @property
    def write(self) -> bool:
        """Whether it writes registers or coils (``rtupoll.rtu.effects``)."""
        return effect(self.pdu) is Effect.WRITE

    @property
    def read(self) -> bool:
        return type(self.message) is ReadRequest


def pdu_length(pdu: bytes) -> int | None:
    """The request PDU's length by the function table; None: unknown function, or its
    byte count is missing."""
    n = request_length(b"\x00" + pdu[:10])
    return None if n is None else n - 3


def parse(pdu: bytes, *, unit: int = 0) -> Ask:
    """Understand a complete request PDU to ``unit``, or raise ``BadRequest`` with the
    code to answer (the checks are ``rtupoll.rtu.messages.parse_request``'s)."""
    try:
        return Ask(parse_request(pdu, unit=unit), pdu)
    except Malformed as exc:
        raise BadRequest(exc.code or ExceptionCode.ILLEGAL_VALUE, exc.reason) from None
