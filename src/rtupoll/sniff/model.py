"""What the sniffer knows about the bus: every unit seen, its health and its latest fields.

Fed ``rtu.stream.Transaction``s, it keeps per unit what the other master saw: requests,
replies, reply times, exceptions, timeouts and garbled replies, and the registers the
replies carried. A unit named ``PROFILE@ADDRESS`` (or in the site file) is decoded
through its profile; any other unit keeps its raw registers, and when what it answered
fits a bundled profile's identify rules (``model.identify.check_passes``) it "looks like"
that profile. A failed transaction yields records with no value (status timeout,
garbled or exception), never a stale or misread one. Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from rtupoll.errors import DeviceException
from rtupoll.model.identify import check_passes
from rtupoll.model.interpret import FieldValue, interpret
from rtupoll.model.profile import Field, Profile
from rtupoll.model.record import failed_record, iso_time, poll_record, record
from rtupoll.model.scaling import Unscaled, scale
from rtupoll.percentiles import quantile
from rtupoll.rtu import messages
from rtupoll.rtu.functions import Table
from rtupoll.rtu.stream import Seen, Transaction

RATE_WINDOW = 10.0  # seconds over which the request rate is measured
REPLY_WINDOW = 1000  # reply times kept for the percentiles


@dataclass(frozen=True)
class Known:
    """A device the user named: a profile at an address, and what to call it."""

    name: str
    profile: Profile
    address: int


def function_of(req: Seen) -> int:
    """The request's function code (a refused one's without the exception bit)."""
    return (req.function or 0) & 0x7F


def describe(req: Seen) -> str:
    """What the request asks, as the sniffer's lines say it: ``fc03 read holding 0x0010
    x2``, or for any other function (or a refused request: why) only the function."""
    fc = function_of(req)
    if isinstance(req, messages.TableRequest):
        verb = "read" if isinstance(req, messages.ReadRequest) else "write"
        return f"fc{fc:02d} {verb} {req.table.value} 0x{req.address:04X} x{req.count}"
    why = f": {req.reason}" if isinstance(req, messages.Malformed) else ""
    return f"fc{fc:02d} function {fc:#04x}{why}"


def carried_words(tx: Transaction, req: Seen | None) -> tuple[int, ...] | None:
    """The registers (or bits) a successful transaction carried: read or written.

    ``req`` is the transaction's ``asked`` (the caller has it already)."""
    answer = tx.answer(req)
    if isinstance(answer, messages.ReadReply):
        return answer.values
    if answer is not None and isinstance(req, messages.WriteSingle | messages.WriteMultiple):
        return req.values
    return None


@dataclass
class Unit:
    """One unit id seen on the line, and its health as the other master sees it."""

    unit: int
    known: Known | None = None
    requests: int = 0
    ok: int = 0
    timeouts: int = 0
    garbled: int = 0
    exceptions: Counter[int] = field(default_factory=Counter)
    reply_times: deque[float] = field(default_factory=lambda: deque(maxlen=REPLY_WINDOW))
    recent: deque[float] = field(default_factory=deque)  # request times, for the rate
    last_seen: float = 0.0
    latest: dict[str, tuple[float, FieldValue]] = field(default_factory=dict)
    failed: dict[str, tuple[float, str]] = field(default_factory=dict)  # field -> status
    image: dict[tuple[Table, int], int] = field(default_factory=dict)  # latest raw words
    refused: dict[tuple[Table, int], int] = field(default_factory=dict)  # exception codes
    answered: set[int] = field(default_factory=set)  # functions answered normally
    reads: set[tuple[Table, int, int]] = field(default_factory=set)
    hints: list[str] = field(default_factory=list)
    hints_stale: bool = False  # answered, reads, image or refused changed since the hints

    @property
    def name(self) -> str:
        return self.known.name if self.known else f"unit {self.unit}"

    def rate(self, now: float) -> float:
        while self.recent and self.recent[0] < now - RATE_WINDOW:
            self.recent.popleft()
        return len(self.recent) / RATE_WINDOW

    def p50(self) -> float | None:
        return quantile(self.reply_times, 50)

    def p95(self) -> float | None:
        return quantile(self.reply_times, 95)


class BusView:
    """Every unit seen, the line's own troubles, and the records to print."""

    def __init__(self, known: Sequence[Known] = (), library: Sequence[Profile] = ()) -> None:
        self.units: dict[int, Unit] = {k.address: Unit(k.address, k) for k in known}
        self.library = [p for p in library if p.identify]
        self.noise = 0  # stray bytes events
        self.broken = 0  # CRC-bad frames answering no request
        self.orphans = 0  # replies to no request seen
        self.broadcasts = 0
        self.transactions = 0
        self.first: float | None = None
        self.last: float = 0.0

    def unit(self, address: int) -> Unit:
        if address not in self.units:
            self.units[address] = Unit(address)
        return self.units[address]

    def add(self, tx: Transaction) -> list[dict[str, Any]]:
        """Take in one transaction; returns the JSON records it yields (POLL_KEYS)."""
        self.first = tx.time if self.first is None else self.first
        end = tx.reply.end if tx.reply else (tx.request.end if tx.request else tx.time)
        self.last = max(self.last, end)
        if tx.status == "noise":
            self.noise += 1
            return []
        if tx.status == "broken":
            self.broken += 1
            return []
        if tx.status == "orphan":
            self.orphans += 1
            return []
        if tx.status == "broadcast":
            self.broadcasts += 1
            return []
        assert tx.request is not None
        self.transactions += 1
        u = self.unit(tx.request.data[0])
        u.requests += 1
        u.recent.append(tx.time)
        u.rate(tx.time)  # keeps the window's times only
        u.last_seen = end
        req = tx.asked
        assert req is not None
        if tx.status == "ok":
            u.ok += 1
            if tx.reply_time is not None:
                u.reply_times.append(tx.reply_time)
            fc = function_of(req)
            if fc not in u.answered:
                u.answered.add(fc)
                u.hints_stale = True
        elif tx.status == "exception":
            code = tx.exception or 0
            u.exceptions[code] += 1
            if isinstance(req, messages.TableRequest) and \
                    u.refused.get((req.table, req.address)) != code:
                u.refused[req.table, req.address] = code
                u.hints_stale = True
        elif tx.status == "timeout":
            u.timeouts += 1
        elif tx.status == "garbled":
            u.garbled += 1
        got = carried_words(tx, req)
        if got is not None:
            assert isinstance(req, messages.TableRequest)
            block = (req.table, req.address, req.count)
            if isinstance(req, messages.ReadRequest) and block not in u.reads:
                u.reads.add(block)
                u.hints_stale = True
            for i, w in enumerate(got):
                if u.image.get((req.table, req.address + i)) != w:
                    u.image[req.table, req.address + i] = w
                    u.hints_stale = True
        if u.known is None:
            # the hints follow from answered, reads, image and refused alone
            if (got is not None or tx.status == "exception") and u.hints_stale:
                u.hints = self.looks_like(u)
                u.hints_stale = False
            return self._raw_records(u, tx, req, got, end)
        return self._records(u, tx, req, got, end)

    # -- records --------------------------------------------------------------
    def _records(self, u: Unit, tx: Transaction, req: Seen,
                 got: tuple[int, ...] | None, end: float) -> list[dict[str, Any]]:
        k = u.known
        assert k is not None
        if not isinstance(req, messages.ReadRequest):
            return []
        start = req.address
        fields = [f for f in k.profile.fields if f.table is req.table
                  and f.address < start + req.count and f.end > start]
        fields.sort(key=lambda f: bool(f.scale_by))  # a frame's factors before what they scale
        out: list[dict[str, Any]] = []
        stamp = iso_time(end)
        for f in fields:
            inside = f.address >= start and f.end <= start + req.count
            if got is not None and inside:
                fv = interpret(f, got[f.address - start : f.end - start])
                # scale_by: times the factors' latest values seen (the other master reads them)
                scaled = scale(fv, {n: v for n, (_, v) in u.latest.items()})
                if isinstance(scaled, Unscaled):
                    u.latest.pop(f.name, None)
                    u.failed[f.name] = (end, "unscaled")
                    out.append(poll_record(stamp, failed_record(
                        k.name, k.profile.id, k.address, f.name, f.unit), "unscaled",
                        scaled.reason))
                    continue
                fv = scaled
                u.latest[f.name] = (end, fv)
                u.failed.pop(f.name, None)
                out.append(poll_record(stamp, record(k.name, k.profile.id, k.address, fv)))
            elif got is None:
                u.failed[f.name] = (end, tx.status)
                out.append(poll_record(stamp, failed_record(
                    k.name, k.profile.id, k.address, f.name, f.unit), tx.status, tx.note))
            # else only part of the field was read: nothing to say about it
        return out

    def _raw_records(self, u: Unit, tx: Transaction, req: Seen,
                     got: tuple[int, ...] | None, end: float) -> list[dict[str, Any]]:
        """A unit with no profile: one record per register read, ``TABLE:ADDRESS``."""
        if got is None or not isinstance(req, messages.ReadRequest):
            return []
        stamp = iso_time(end)
        return [{"time": stamp, "device": u.name, "profile": None, "address": u.unit,
                 "field": f"{req.table.value}:{req.address + i}", "value": w, "unit": "",
                 "raw": [w], "severity": "ok", "text": f"0x{w:04X}", "status": "ok",
                 "error": ""} for i, w in enumerate(got)]

    # -- "looks like" ----------------------------------------------------------
    def looks_like(self, u: Unit) -> list[str]:
        """Bundled profiles whose identify rules what ``u`` answered satisfies, best first.

        A profile fits when at least one of its checks could be evaluated from the
        registers seen, every check that could passed, every function the unit answered
        is one the profile supports, and every block the master read holds one of its
        fields.
        """
        ranked: list[tuple[int, str, str]] = []
        for p in self.library:
            if any(fn not in p.limits.functions for fn in u.answered):
                continue
            if any(not any(f.table is t and f.address < a + n and f.end > a for f in p.fields)
                   for t, a, n in u.reads):
                continue
            passed: list[str] = []
            for check in p.identify:
                f = p.field(check.field)
                outcome = self._outcome(u, f)
                if outcome is None:
                    continue
                why = check_passes(check, p, u.unit, outcome)
                if why is None:
                    passed = []
                    break
                passed.append(why)
            else:
                if passed:
                    ranked.append((-len(passed), p.id, f"{p.id} ({'; '.join(passed)})"))
        return [text for _, _, text in sorted(ranked)]

    def _outcome(self, u: Unit, f: Field) -> tuple[int, ...] | DeviceException | None:
        words = [u.image.get((f.table, r)) for r in range(f.address, f.end)]
        if all(w is not None for w in words):
            return tuple([w for w in words if w is not None])
        code = u.refused.get((f.table, f.address))
        return DeviceException(code, unit=u.unit) if code is not None else None
