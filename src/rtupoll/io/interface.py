"""The one bus interface: what polling, scan, writes, commissioning and the gateway
need of a bus, whichever carries the bytes.

``rtupoll.io.bus.Bus`` (a serial port or an RTU-over-TCP gateway, through pymodbus)
and ``rtupoll.io.virtual.VirtualBus`` (the simulator's engine called directly, for
tests whose subject is not the port) both are one, as python-can's buses are one
``BusABC``. Errors are the ``rtupoll.errors`` bus errors: ``DeviceTimeout``,
``FrameError``, ``DeviceException``, ``PortError``, ``RefusedError``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import Line


class BusLike(Protocol):
    framing: Framing

    async def open(self) -> None: ...

    async def close(self) -> None: ...

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0) -> tuple[int, ...]:
        """Registers as 16-bit ints; coils and discrete inputs as 0/1."""
        ...

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        """FC06 or FC16; True when the device echoed (``reply``: see ``Bus``)."""
        ...

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None: ...

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0) -> bytes:
        """Any request PDU; the reply PDU (an exception PDU when the device sent one)."""
        ...

    def late(self, unit: int) -> int:
        """Replies from ``unit`` that came after their request had timed out."""
        ...


class LineEvidence:
    """What a bus tells about its line, read from its ``rtu.line.Line``: shared by
    ``Bus`` and ``VirtualBus`` (the learned timeouts and the statistics use it)."""

    line: Line

    def late(self, unit: int) -> int:
        """Late replies from ``unit``: answers to requests that had timed out."""
        return int(self.line.counts.late[unit])

    def reply_time(self, unit: int) -> float | None:
        """``unit``'s last reply time (request's end to reply's first byte), if any."""
        return self.line.reply_time.get(unit)

    def late_reply_time(self, unit: int) -> float | None:
        """The reply time of ``unit``'s last late reply, if it sent one."""
        return self.line.late_reply_time.get(unit)

    def set_patience(self, unit: int, seconds: float) -> None:
        """Count ``unit``'s late window in ``seconds`` when its timeout is shorter
        (``Line.patience``: a learned timeout does not shorten it)."""
        self.line.patience[unit] = seconds
