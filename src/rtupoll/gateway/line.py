"""How a client's request PDU reaches the RTU line: ``Line.transact``.

``transact(unit, pdu, *, timeout, retries) -> reply PDU`` puts one request on the
line through the bus discipline (one transaction at a time, silence, drain after a
timeout) and returns the device's reply PDU, normal or exception (function | 0x80;
b"" for a broadcast); it raises ``DeviceTimeout``, ``FrameError`` or ``PortError``,
and ``RefusedError`` for a request the bus cannot send. Every
``rtupoll.io.interface.BusLike`` (the scheduler's buses) is one.
"""

from __future__ import annotations

from typing import Protocol


class Line(Protocol):
    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0) -> bytes: ...
