"""RTU frames over TCP (``--serve rtu+tcp://``), sans-IO: what serial-to-Ethernet
converters in "transparent" mode carry, for clients that speak RTU only.

A frame is ``unit, PDU, CRC``; its length follows from the function table. A frame
with a bad CRC or an unknown function cannot be delimited with confidence, so, as
with a malformed MBAP frame, the connection is closed (``MbapError``).
"""

from __future__ import annotations

from rtupoll.gateway.mbap import Frame, MbapError
from rtupoll.rtu import with_crc
from rtupoll.rtu.frames import NEED_MORE, Direction, frame_at, lengths
from rtupoll.rtu.functions import FUNCTIONS, MAX_PDU


class RtuDecoder:
    """Splits a client's byte stream into RTU request frames."""

    def __init__(self) -> None:
        self.buffer = b""

    def feed(self, data: bytes) -> list[Frame]:
        self.buffer += data
        out: list[Frame] = []
        while len(self.buffer) >= 2:
            n = frame_at(self.buffer, direction=Direction.REQUEST)
            if n == NEED_MORE:
                if len(self.buffer) > MAX_PDU + 3:
                    raise MbapError("no frame in 256 bytes")
                break
            if n < 0:  # not a frame: say why, then close
                fc = self.buffer[1]
                if fc not in FUNCTIONS:
                    raise MbapError(f"function {fc} unknown: cannot tell where the frame ends")
                size = lengths(self.buffer[:11], Direction.REQUEST)[0]
                raise MbapError(f"CRC error in {self.buffer[:size][:12].hex(' ')}")
            frame, self.buffer = self.buffer[:n], self.buffer[n:]
            out.append(Frame(None, frame[0], frame[1:-2]))
        return out


def encode(unit: int, pdu: bytes) -> bytes:
    return with_crc(bytes((unit,)) + pdu)
