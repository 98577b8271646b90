"""One master transaction, sans-IO: the request's checks, its attempts, its outcome.

Written once for every bus (``rtupoll.io.bus.Bus`` on a port, ``rtupoll.sim.virtual.
VirtualBus`` on the simulator's engine): each is a thin driver that does what a
``Transaction`` says and tells it what happened, with the time. Like ``Line`` below
it, this module does no I/O and reads no clock.

The driver's loop::

    tx = Transaction(line, request, timeout=0.5, retries=2)
    wait (not holding the bus) until tx.hazard_until(now) <= now   # Line.hazard_until
    take the bus
    while True:
        step = tx.next()
        Send(frame, at):  wait until ``at`` (bytes that arrive meanwhile go to
                          tx.received, and ``at`` may move: ask next() again), write
                          ``frame``, call tx.sent(now)
        Await(until):     hand every byte to tx.received(data, now); when it returns
                          True ask next(); at ``until`` call tx.expired(now)
        Done / Failed:    the transaction is over; stats.add(tx, busy)

**The rules.** An attempt is bounded by the timeout plus the request's and the
normal reply's wire time (a slow baud rate does not eat the device's time). The
first attempt honours the line's drain, a retry only the silence. An attempt ends
with an answer (``Done``, or ``Failed("exception")`` for an exception reply, which
is not retried), a garbled reply known at once (``Line``: retried after the
silence), or its deadline (``Line.expire`` says timeout or garbled; retried). When
the attempts are spent the last failure is the outcome; a write whose echo the
caller does not require (``tolerate``) ends ``Done(b"", "unconfirmed")`` instead. A
broadcast (unit 0) ends when it is sent: ``Done(b"", "broadcast")``, and the line
gives the devices ``turnaround`` to act on it.

**Timing evidence** is in the values: ``Done.reply_time`` (and an exception reply's
``Failed.reply_time``) is the answer's reply time (``Answer.reply_time``), and
``Transaction.evidence`` what the transaction tells of its unit's timing as one value
(``Evidence``: that reply time, the unit's late replies so far, the attempts made), which
a read returns with its values (``ReadResult``). How long a late reply to the request stays
expected is the request's own (``patience``, ``Line.expire``), not the line's state.
So is the silence its unit needs before it (``idle_gap``): that one the line keeps for
the unit (``Line.set_idle_gap``), because it is owed before every request to the
device, whoever sends it (the gateway's pass-through, a write, a bisection's reads).

**Request checks** (``read_request``, ``write_registers_request``,
``write_coil_request``: a message of ``rtu.messages``, which encodes its own frame;
``pdu_frame``: any other request PDU, passed through as bytes) build a request or raise
``Refused`` (nothing is sent): the quantity limits are ``rtu.functions.MAX_QUANTITY``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import field

from rtupoll.frozen import frozen, mutable
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.functions import (
    FUNCTION_NAMES,
    MAX_QUANTITY,
    Table,
    answer_length,
    request_length,
)
from rtupoll.rtu.line import Answer, Garbled, Line
from rtupoll.rtu.messages import ReadRequest, WriteMultiple, WriteSingle

# BusStats.outcomes keys: one per transaction ("unconfirmed": a tolerated write without echo)
OUTCOMES = ("ok", "timeout", "frame", "exception", "port", "broadcast", "unconfirmed")


class Refused(ValueError):
    """A request that must not be sent (the bus raises ``RefusedError``)."""


@mutable(slots=True)  # made per transaction: plain, not frozen (CPU)
class Send:
    """Put ``frame`` on the wire at ``at`` (then call ``Transaction.sent``)."""

    frame: bytes
    at: float


@mutable(slots=True)  # made per transaction: plain, not frozen (CPU)
class Await:
    """Hand received bytes to ``Transaction.received``; at ``until``, ``expired``."""

    until: float


@mutable(slots=True)  # made per transaction: plain, not frozen (CPU)
class Done:
    """The answer frame (b"" for a broadcast or an unconfirmed write)."""

    frame: bytes
    outcome: str = "ok"  # ok, broadcast or unconfirmed
    reply_time: float | None = None  # the answer's (``Answer.reply_time``)


@frozen
class Failed:
    """No answer: ``kind`` is timeout, frame (garbled) or exception (``code``)."""

    kind: str
    why: str
    unit: int
    function: int
    code: int = 0
    # an exception reply's (``Answer.reply_time``)
    reply_time: float | None = field(default=None, compare=False)

    @property
    def outcome(self) -> str:
        return self.kind


Step = Send | Await | Done | Failed


class Transaction:
    """One request, its attempts and its outcome. See the module docstring."""

    def __init__(self, line: Line, request: bytes, *, timeout: float, retries: int = 0,
                 tolerate: bool = False, turnaround: float = 0.1,
                 patience: float = 0.0, idle_gap: float | None = None) -> None:
        """``patience``: how long a late reply is still expected when that is longer
        than ``timeout`` (``Line.expire``: a learned timeout does not shorten it).
        ``idle_gap``: the silence the unit needs before a request (None: as the line
        has it, ``Line.set_idle_gap``), kept by the line for the unit."""
        if not 0 < timeout <= 60 or retries < 0:
            raise Refused(f"timeout {timeout} s / retries {retries} make no sense")
        self.line, self.request, self.unit = line, request, request[0]
        if idle_gap is not None:  # (the usual 0.0 of an unset gap: one look-up)
            line.set_idle_gap(self.unit, idle_gap)
        self.timeout, self.retries, self.tolerate = timeout, retries, tolerate
        self.patience = patience
        self.turnaround = turnaround
        framing = line.framing
        self.limit = timeout + framing.wire_time(len(request) + (answer_length(request) or 0))
        self.attempts = 0  # requests put on the wire
        self.wire = 0.0  # seconds of this transaction's frames on the wire
        self.result: Done | Failed | None = None
        self.deadline = float("inf")  # the attempt in flight's
        self._event: Answer | Garbled | None = None
        self._in_flight = False
        self._failure: Failed | None = None  # the last attempt's, once one failed

    @property
    def outcome(self) -> str:
        """The ``OUTCOMES`` key (before the end: the outcome so far)."""
        return self.result.outcome if self.result is not None else "ok"

    @property
    def heard(self) -> bool:
        """The attempt that just ended was ended by the line (an answer or a garbled
        reply), not by its deadline."""
        return self._event is not None or self.result is not None

    def hazard_until(self, now: float) -> float:
        """Until when the request must not go (``Line.hazard_until``): wait for it
        without holding the bus; 0 (or a past time) when it may go now."""
        return self.line.hazard_until(self.request, now)

    def ready_at(self) -> float:
        """When the next attempt may go: the first honours the drain, a retry only the
        silence (the unit's idle gap, the request's ``idle_gap``, for both)."""
        return self.line.ready_at(drain=self.attempts == 0, unit=self.unit)

    def next(self) -> Step:
        """What the driver does now."""
        if self.result is not None:
            return self.result
        if self._in_flight:
            event = self._event
            if event is None:
                return Await(self.deadline)
            self._in_flight, self._event = False, None
            if isinstance(event, Answer):
                return self._answered(event)
            self._failed("frame", event.why)
            if event.final:  # (an echo: a retry would come back the same)
                return self._give_up()
        if self.attempts > self.retries:
            return self._give_up()
        return Send(self.request, self.ready_at())

    def sent(self, now: float) -> None:
        """The request started on the wire at ``now``."""
        framing = self.line.framing
        self.line.send(self.request, now, self.attempts > 0)  # (a retry after the first)
        self.attempts += 1
        self.wire += framing.wire_time(len(self.request))
        if self.unit == 0:  # a broadcast: nobody answers
            self.line.after_broadcast(self.turnaround)
            self.result = Done(b"", "broadcast")
            return
        self._in_flight, self._event = True, None
        self.deadline = now + self.limit

    def received(self, data: bytes, now: float) -> bool:
        """Bytes arrived at ``now`` (at any time: the line counts the silence from
        them). True when the attempt in flight is over: ask ``next()``."""
        event = self.line.receive(data, now)
        if event is None or not self._in_flight:
            return False
        self._event = event
        return True

    def expired(self, now: float) -> None:
        """The attempt's deadline passed (``now``) with no answer."""
        if not self._in_flight or self._event is not None:
            return
        self._in_flight = False
        att = self.line.attempt
        rx = bytes(att.rx) if att is not None else b""
        why = self.line.expire(now, self.timeout, self.patience)
        if why:
            self._failed("frame", why)
        else:
            ignored = f" (ignored: {rx[:16].hex(' ')})" if rx else ""
            self._failed("timeout", f"no reply from unit {self.request[0]} to {self._what} "
                                    f"within {self.timeout:g} s", ignored)

    # -- outcomes --------------------------------------------------------------------

    @property
    def _what(self) -> str:
        fn = self.request[1]
        return FUNCTION_NAMES.get(fn, f"function {fn}")

    def _tries(self) -> str:
        return f" ({self.attempts} tries)" if self.attempts > 1 else ""

    def _failed(self, kind: str, why: str, after: str = "") -> None:
        unit, fn = self.request[0], self.request[1]
        text = why if kind == "timeout" else f"unit {unit}, {self._what}: {why}"
        self._failure = Failed(kind, text + self._tries() + after, unit, fn)

    def _answered(self, answer: Answer) -> Done | Failed:
        frame = answer.frame
        self.wire += self.line.framing.wire_time(len(frame))
        if frame[1] & 0x80:
            self.result = Failed("exception", f"exception {frame[2]}", frame[0],
                                 self.request[1], frame[2], answer.reply_time)
        else:
            self.result = Done(frame, "ok", answer.reply_time)
        return self.result

    def evidence(self) -> Evidence:
        """What this transaction (over, or failed) tells of its unit's timing."""
        result, line, unit = self.result, self.line, self.unit
        # (get: a Counter's missing key costs a Python call, and this is once a transaction)
        return Evidence(result.reply_time if result is not None else None,
                        line.counts.late.get(unit, 0), line.late_reply_time.get(unit),
                        self.attempts)

    def _give_up(self) -> Done | Failed:
        failure = self._failure or Failed("timeout", f"no reply from unit {self.request[0]}",
                                          self.request[0], self.request[1])
        self.result = Done(b"", "unconfirmed") if self.tolerate else failure
        return self.result


@mutable
class BusStats:
    """What a bus did. ``busy`` over elapsed time is the bus's utilisation."""

    transactions: int = 0  # read/write calls completed, whatever the outcome
    attempts: int = 0  # requests put on the wire, retries included
    retries: int = 0
    busy: float = 0.0  # seconds the bus was held: silences, requests, replies, timeouts, drains
    wire: float = 0.0  # seconds of frames on the wire at the baud rate (the physical floor)
    outcomes: Counter[str] = field(default_factory=Counter)  # see OUTCOMES

    def utilisation(self, elapsed: float) -> float:
        return min(1.0, self.busy / elapsed) if elapsed > 0 else 0.0

    def add(self, tx: Transaction, busy: float, *, outcome: str | None = None) -> None:
        """A transaction is over (``outcome``: the driver's own, e.g. "port")."""
        self.transactions += 1
        self.attempts += tx.attempts
        self.retries += max(0, tx.attempts - 1)
        self.busy += busy
        self.wire += tx.wire
        self.outcomes[outcome or tx.outcome] += 1


@mutable(slots=True)  # made per transaction: plain, not frozen (CPU)
class Evidence:
    """What one transaction tells of its unit's timing (``rtupoll.jobs.timeouts`` learns
    from it): its answer's reply time (None: no answer, or a broadcast), the late replies
    the line has heard from the unit so far and the last one's reply time, and the
    requests put on the wire (retries included)."""

    reply_time: float | None = None
    late: int = 0  # replies that came after their request had timed out, the unit's so far
    late_reply_time: float | None = None  # the last late reply's
    attempts: int = 0


@mutable(slots=True)  # made per read: plain, not frozen (CPU)
class ReadResult:
    """A read's outcome as one value: the values (registers as 16-bit ints, coils and
    discrete inputs as 0/1) and the transaction's ``Evidence``."""

    values: tuple[int, ...]
    evidence: Evidence


# -- requests, checked before anything is sent -----------------------------------------


def check_unit(unit: int, *, broadcast: bool) -> None:
    if not (0 if broadcast else 1) <= unit <= 255:
        what = "0..255 (0: broadcast)" if broadcast else "1..255 (a read cannot be broadcast)"
        raise Refused(f"unit {unit} is outside {what}")


def read_request(unit: int, table: Table, address: int, count: int) -> ReadRequest:
    """A read request, or ``Refused``."""
    check_unit(unit, broadcast=False)
    most = MAX_QUANTITY[table.read_function]
    if not 1 <= count <= most or not address >= 0 or address + count > 0x10000:
        raise Refused(f"cannot read {count} {table.value} from 0x{address:X} "
                      f"(1..{most} within 0..65535)")
    return ReadRequest(unit, table.read_function, address, count)


def write_registers_request(unit: int, address: int, values: Sequence[int], *,
                            function: int = 16) -> WriteSingle | WriteMultiple:
    """A write of registers (FC06: one value, FC16), or ``Refused``."""
    check_unit(unit, broadcast=True)
    vals = [int(v) for v in values]
    if function not in (6, 16) or (function == 6 and len(vals) != 1) or \
            not 1 <= len(vals) <= MAX_QUANTITY[16] or address < 0 or \
            address + len(vals) > 0x10000 or any(not 0 <= v <= 0xFFFF for v in vals):
        raise Refused(f"cannot write {vals} at 0x{address:X} with function {function}")
    return WriteSingle(unit, 6, address, vals[0]) if function == 6 else \
        WriteMultiple(unit, 16, address, tuple(vals))


def write_coil_request(unit: int, address: int, on: bool) -> WriteSingle:
    check_unit(unit, broadcast=True)
    if not 0 <= address <= 0xFFFF:
        raise Refused(f"coil address {address} is outside 0..65535")
    return WriteSingle(unit, 5, address, int(on))


def pdu_frame(unit: int, pdu: bytes) -> bytes:
    """Any request PDU (function code and data) to ``unit`` as a frame, or ``Refused``."""
    check_unit(unit, broadcast=True)
    request = with_crc(bytes((unit,)) + pdu)
    if not pdu or request_length(request) != len(request):
        raise Refused(f"function 0x{pdu[:1].hex()} with {len(pdu) - 1} data bytes "
                      "is not a request this bus can send")
    return request
