"""Modbus TCP's MBAP framing, sans-IO: a TCP byte stream in, requests out; replies to bytes.

An MBAP frame is a 7-byte header -- transaction id, protocol id (0 for Modbus), length
(of what follows: the unit id and the PDU), unit id -- and the PDU. A TCP stream may
split a frame or carry several, so ``MbapDecoder.feed`` keeps what is incomplete.

A frame that cannot be trusted ends the connection (``MbapError``): a protocol id
other than 0, a length outside 2..254 (a PDU is at most 253 bytes), or a length that
contradicts the PDU's own (by the function table: a read is always 5 bytes, a
multiple write carries its byte count). After such a frame there is no telling where
the next one starts, so answering is not an option; closing is what the Modbus TCP
specification's implementation guide does too.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from rtupoll.errors import ClientError
from rtupoll.gateway.pdu import pdu_length
from rtupoll.rtu.functions import MAX_PDU
from rtupoll.rtu.messages import ExceptionReply

HEADER = 7  # transaction id, protocol id, length, unit id


class MbapError(ClientError):
    """A frame that ends the connection; the message says why, for the log."""


@dataclass(frozen=True)
class Frame:
    """One request: its transaction id (None in RTU over TCP), unit id and PDU."""

    tid: int | None
    unit: int
    pdu: bytes


class MbapDecoder:
    """Splits a client's byte stream into request frames."""

    def __init__(self) -> None:
        self.buffer = b""

    def feed(self, data: bytes) -> list[Frame]:
        """New bytes -> complete frames, in order; raises ``MbapError`` on a bad one."""
        self.buffer += data
        out: list[Frame] = []
        while len(self.buffer) >= HEADER:
            tid, proto, length, unit = struct.unpack_from(">HHHB", self.buffer)
            if proto != 0:
                raise MbapError(f"protocol id {proto} is not 0 (Modbus)")
            if not 2 <= length <= MAX_PDU + 1:
                raise MbapError(f"MBAP length {length} is outside 2..{MAX_PDU + 1} "
                                f"(a PDU of {length - 1} bytes)")
            end = HEADER - 1 + length
            if len(self.buffer) < end:
                break
            pdu = self.buffer[HEADER:end]
            own = pdu_length(pdu)
            if own is not None and own != len(pdu):
                raise MbapError(f"MBAP length {length} does not match the PDU "
                                f"(function {pdu[0]} takes {own} bytes, got {len(pdu)})")
            out.append(Frame(tid, unit, pdu))
            self.buffer = self.buffer[end:]
        return out


def encode(tid: int, unit: int, pdu: bytes) -> bytes:
    """An MBAP frame carrying ``pdu`` (a reply) for transaction ``tid``."""
    return struct.pack(">HHHB", tid & 0xFFFF, 0, len(pdu) + 1, unit) + pdu


def encode_exception(tid: int, unit: int, function: int, code: int) -> bytes:
    return encode(tid, unit, ExceptionReply(unit, function, code).pdu())
