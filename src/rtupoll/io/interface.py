"""The one bus interface: what polling, scan, writes, commissioning and the gateway
need of a bus, whichever carries the bytes.

``rtupoll.io.bus.Bus`` (a serial port or an RTU-over-TCP gateway, through pymodbus)
and ``rtupoll.sim.virtual.VirtualBus`` (the simulator's engine called directly, for
tests whose subject is not the port) both are one, as python-can's buses are one
``BusABC``. Errors are the ``rtupoll.errors`` bus errors: ``DeviceTimeout``,
``FrameError``, ``DeviceException``, ``PortError``, ``RefusedError``.

**Timing is in the values.** A read returns its values and its evidence as one value
(``ReadResult``: the reply time, the unit's late replies so far, the attempts); a bus error
carries its transaction's (``BusError.evidence``). How long a late reply stays expected
is passed with the request (``patience``), and so is the silence the unit needs before
it (``idle_gap``: the line keeps it for the unit's later requests, whoever sends them,
``rtu.line``). What the line heard from a unit between its
requests (late replies to requests that timed out) is a live view, ``unit_counts``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import NoReturn, Protocol, TypeVar

from rtupoll.errors import (
    BusError,
    DeviceException,
    DeviceTimeout,
    FrameError,
    RefusedError,
    UsageError,
)
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import Line, UnitCounts
from rtupoll.rtu.messages import (
    Malformed,
    ReadReply,
    ReadRequest,
    Reply,
    Request,
    parse_reply,
)
from rtupoll.rtu.transaction import (
    Await,
    BusStats,
    Done,
    Failed,
    ReadResult,
    Refused,
    Send,
    Transaction,
    pdu_frame,
    read_request,
    write_coil_request,
    write_registers_request,
)

REPLY_MODES = ("echo", "none", "malformed", "any")
R = TypeVar("R")


class BusLike(Protocol):
    framing: Framing
    adapter_latency: float  # a USB adapter's latency timer, added to every reply's time

    @property
    def echo_found(self) -> bool:
        """An echo came back without ``echo`` set (``Line.adopt_echo``: now consumed)."""
        ...

    @property
    def stats(self) -> BusStats | None:
        """What the bus did (``BusStats``: its busy time, its attempts); None: a bus that
        counts nothing."""
        ...

    async def open(self) -> None: ...

    async def close(self) -> None: ...

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        """The values (registers as 16-bit ints; coils and discrete inputs as 0/1) and the
        evidence; ``patience``: how long a late reply stays expected, when longer than
        ``timeout``; ``idle_gap``: the silence ``unit`` needs before a request (None: as
        the line has it)."""
        ...

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        """FC06 or FC16; True when the device echoed (``reply``: see ``Bus``)."""
        ...

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None: ...

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0, idle_gap: float | None = None) -> bytes:
        """Any request PDU; the reply PDU (an exception PDU when the device sent one).
        ``idle_gap``: as ``read``'s."""
        ...

    def unit_counts(self, unit: int) -> UnitCounts:
        """What the line counts of ``unit`` (late replies, attempts by how they ended, its
        idle gap): a live view, read when asked."""
        ...


class LineBus:
    """The one implementation of ``BusLike`` over ``rtu.transaction``: requests are
    checked and built here, each becomes a ``Transaction``, and a subclass only drives
    it (``_run``: the port's ``Bus``, the simulator's ``VirtualBus``). A read's evidence
    is its transaction's (``Transaction.evidence``); what the line counts of a unit is
    read from the one ``rtu.line.Line`` (``unit_counts``)."""

    line: Line
    stats: BusStats
    adapter_latency: float = 0.0
    broadcast_turnaround: float = 0.1

    async def _run(self, tx: Transaction) -> Done:
        """``tx`` on the bus (its lock, its clock): ``_drive(tx)``."""
        raise NotImplementedError

    async def _step(self, tx: Transaction, step: Send | Await) -> None:
        """Do what ``step`` says (send at its time; wait for bytes until its time)."""
        raise NotImplementedError

    async def _drive(self, tx: Transaction) -> Done:
        """Drive ``tx`` to its end: its ``Done``, or the bus error of its ``Failed``."""
        while True:
            step = tx.next()
            if isinstance(step, Done):
                return step
            if isinstance(step, Failed):
                raise_failed(step)
            await self._step(tx, step)

    async def _transact(self, request: bytes, timeout: float, retries: int, *,
                        tolerate: bool = False, patience: float = 0.0,
                        idle_gap: float | None = None) -> Transaction:
        """``request``'s transaction, over (its ``result`` a ``Done``); a bus error
        carries its evidence."""
        try:
            tx = Transaction(self.line, request, timeout=timeout, retries=retries,
                             tolerate=tolerate, turnaround=self.broadcast_turnaround,
                             patience=patience, idle_gap=idle_gap)
        except Refused as exc:
            raise UsageError(str(exc)) from None
        try:
            await self._run(tx)
        except BusError as exc:
            exc.evidence = tx.evidence()
            raise
        return tx

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        """The values (registers as 16-bit ints; coils and discrete inputs as 0/1) and
        the transaction's evidence, as one value. ``patience``: how long a late reply
        stays expected when longer than ``timeout`` (a learned timeout does not shorten
        it: ``Line.expire``); ``idle_gap``: the silence ``unit`` needs before a request
        (None: as the line has it; kept for the unit, ``Line.set_idle_gap``)."""
        try:
            request, frame = _read(unit, table, address, count)
        except Refused as exc:
            raise RefusedError(str(exc)) from None
        tx = await self._transact(frame, timeout, retries, patience=patience,
                                  idle_gap=idle_gap)
        assert isinstance(tx.result, Done)
        try:
            reply = _reply(request, tx.result.frame)
            if not isinstance(reply, ReadReply):  # (the line took only a normal reply)
                raise FrameError(f"unit {unit}: no read reply: "
                                 f"{tx.result.frame[:16].hex(' ')}")
        except FrameError as error:
            error.evidence = tx.evidence()
            raise
        return ReadResult(reply.values, tx.evidence())

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        """Function 6 (one value) or 16; True when the device confirmed it with an echo.

        With ``reply`` other than "echo" a missing or malformed reply is not an error and
        the write is not repeated (False): the caller verifies by reading back. An
        exception reply is always an error."""
        if reply not in REPLY_MODES:
            raise UsageError(f"reply {reply!r} is not one of: {', '.join(REPLY_MODES)}")
        request = _checked(lambda: write_registers_request(unit, address, values,
                                                           function=function))
        tx = await self._transact(request.frame(), timeout,
                                  retries if reply == "echo" else 0, tolerate=reply != "echo")
        assert isinstance(tx.result, Done)
        if tx.result.frame:
            _reply(request, tx.result.frame)  # (the line took only the write's confirmation)
        return bool(tx.result.frame)

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None:
        request = _checked(lambda: write_coil_request(unit, address, on))
        tx = await self._transact(request.frame(), timeout, retries)
        assert isinstance(tx.result, Done)
        if tx.result.frame:
            _reply(request, tx.result.frame)

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0, idle_gap: float | None = None) -> bytes:
        """Any request PDU (function code and data) to ``unit``; the reply PDU, which is
        an exception PDU (function | 0x80, code) when the device answered with one.
        For a gateway passing other masters' requests through; a broadcast returns b"".
        ``idle_gap``: the silence the device needs before it (None: what the line keeps
        for the unit), as ``read``'s."""
        request = _checked(lambda: pdu_frame(unit, pdu))
        try:
            tx = await self._transact(request, timeout, retries, idle_gap=idle_gap)
        except DeviceException as exc:
            return bytes((pdu[0] | 0x80, exc.code))
        assert isinstance(tx.result, Done)
        return tx.result.frame[1:-2]

    # -- what the line knows ---------------------------------------------------------

    @property
    def echo_found(self) -> bool:
        """An echo came back without ``echo`` set (``Line.adopt_echo``: now consumed)."""
        return self.line.echo_found

    @property
    def unsolicited(self) -> int:
        """Frames and bursts of bytes that answered nothing this bus asked."""
        return int(self.line.counts.unsolicited)

    def unit_counts(self, unit: int) -> UnitCounts:
        """``unit``'s late replies and attempts as the line counts them, and its idle gap:
        a live view."""
        return UnitCounts(self.line, unit)


def raise_failed(failed: Failed) -> NoReturn:
    """The bus error of a transaction that got no answer."""
    if failed.kind == "exception":
        raise DeviceException(failed.code, unit=failed.unit, function=failed.function)
    if failed.kind == "frame":
        raise FrameError(failed.why)
    raise DeviceTimeout(failed.why)


def _checked(build: Callable[[], R]) -> R:
    """The request ``build`` makes, or ``RefusedError`` (nothing is sent)."""
    try:
        return build()
    except Refused as exc:
        raise RefusedError(str(exc)) from None


@functools.lru_cache(maxsize=1024)
def _read(unit: int, table: Table, address: int, count: int) -> tuple[ReadRequest, bytes]:
    """A checked read request and its frame (a poller asks the same few again and again:
    built once each)."""
    request = read_request(unit, table, address, count)
    return request, request.frame()


def _reply(request: Request, frame: bytes) -> Reply:
    """The typed reply (``rtu.messages.parse_reply``) in the answer ``frame`` the line
    took (its CRC checked there), or ``FrameError``."""
    try:
        return parse_reply(request, frame[1:-2], unit=frame[0])
    except Malformed as exc:
        raise FrameError(f"unit {request.unit}: {exc.reason}") from None
