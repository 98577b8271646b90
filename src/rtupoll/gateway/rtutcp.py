"""RTU frames over TCP (``--serve rtu+tcp://``), sans-IO: what serial-to-Ethernet
converters in "transparent" mode carry, for clients that speak RTU only.

A frame is ``unit, PDU, CRC``; its length follows from the function table. A frame
with a bad CRC or an unknown function cannot be delimited with confidence, so, as
with a malformed MBAP frame, the connection is closed (``MbapError``).
"""

from __future__ import annotations

from rtupoll.gateway.mbap import Frame, MbapError
from rtupoll.rtu import crc_ok, with_crc
from rtupoll.rtu.functions import FUNCTIONS, MAX_PDU, request_length


class RtuDecoder:
    """Splits a client's byte stream into RTU request frames."""

    def __init__(self) -> None:
        self.buffer = b""

    def feed(self, data: bytes) -> list[Frame]:
        self.buffer += data
        out: list[Frame] = []
        while len(self.buffer) >= 2:
            fc = self.buffer[1]
            if fc not in FUNCTIONS:
                raise MbapError(f"function {fc} unknown: cannot tell where the frame ends")
            n = request_length(self.buffer[:11])
            if n is None or len(self.buffer) < n:
                if len(self.buffer) > MAX_PDU + 3:
                    raise MbapError("no frame in 256 bytes")
                break
            frame, self.buffer = self.buffer[:n], self.buffer[n:]
            if not crc_ok(frame):
                raise MbapError(f"CRC error in {frame[:12].hex(' ')}")
            out.append(Frame(None, frame[0], frame[1:-2]))
        return out


def encode(unit: int, pdu: bytes) -> bytes:
    return with_crc(bytes((unit,)) + pdu)
