"""What polling has seen: readings, per-device health and per-bus load.

Kept apart from the scheduler so the live table, the JSON/CSV sinks and the
``--once`` summary read one model, and so the numbers can be tested without a bus.
A failed reading carries no value (never a stale one); the last good value of
each field is kept separately, with its time, for the display.
"""

from __future__ import annotations

import enum
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from rtupoll.config.site import DeviceConfig
from rtupoll.model.interpret import FieldValue
from rtupoll.model.profile import Field
from rtupoll.percentiles import quantile

if TYPE_CHECKING:
    from rtupoll.rtu.line import UnitCounts

LATENCY_WINDOW = 1000  # transactions kept for the percentiles
LOAD_WINDOW = 10.0  # seconds over which bus utilisation is measured


class State(str, enum.Enum):
    STARTING = "starting"  # not read yet
    ONLINE = "online"  # the last cycle got a valid reply
    RETRYING = "retrying"  # a few cycles in a row got none; retried with backoff
    OFFLINE = "offline"  # many cycles got none; probed now and then


class Status(str, enum.Enum):
    """What became of one field's reading in one cycle (``status`` in the records)."""

    OK = "ok"  # read and decoded
    TIMEOUT = "timeout"  # no (valid) reply in time
    GARBLED = "garbled"  # a reply that could not be used: CRC, truncated, malformed
    EXCEPTION = "exception"  # the device answered with a Modbus exception
    SKIPPED = "skipped"  # not asked: the device stopped answering earlier in the cycle
    PORT = "port"  # the port was gone (adapter unplugged, gateway down)
    ABSENT = "absent"  # this variant of the device has no such field
    UNSCALED = "unscaled"  # read, but a field it is multiplied by (scale_by) has no value

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class Reading:
    """One field's outcome in one cycle: a value, or why there is none."""

    time: float  # wall clock, seconds since the epoch
    device: DeviceConfig
    field: Field
    value: FieldValue | None
    status: Status = Status.OK
    error: str = ""

    @property
    def ok(self) -> bool:
        return self.value is not None


@dataclass
class DeviceStats:
    """Health of one device since polling started."""

    requests: int = 0
    ok: int = 0
    timeouts: int = 0
    garbled: int = 0  # CRC errors, garbage, truncated or malformed replies
    timeout: float | None = None  # the timeout used now, seconds beyond the wire time
    timeout_source: str = ""  # pinned (the user's) | profile (nothing learned yet) | learned
    # the line's count of the device's attempts (each by how it ended), its idle gap
    line: UnitCounts | None = None
    holes: list[str] = field(default_factory=list)  # registers learned never to bridge, why
    exceptions: Counter[int] = field(default_factory=Counter)
    latencies: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    state: State = State.STARTING
    failures: int = 0  # cycles in a row with no valid reply
    cycles: int = 0
    latest: dict[str, Reading] = field(default_factory=dict)  # field -> this cycle's outcome
    last_good: dict[str, Reading] = field(default_factory=dict)  # field -> last value read
    last_good_time: float | None = None

    def record(self, readings: Sequence[Reading], answered: bool) -> None:
        self.cycles += 1
        self.failures = 0 if answered else self.failures + 1
        latest, last_good = self.latest, self.last_good
        for r in readings:
            name = r.field.name
            latest[name] = r
            if r.value is not None:  # r.ok
                last_good[name] = r
                self.last_good_time = r.time

    @property
    def late(self) -> int:
        """Replies that came after their request had timed out (never decoded), as the
        line counts them."""
        return self.line.late if self.line else 0

    @property
    def exception_count(self) -> int:
        return sum(self.exceptions.values())

    # every attempt, by how it ended (docs/polling.md, "What the table shows"): the
    # transaction counts above say what each read came to, these what the wire did
    @property
    def attempts(self) -> int:
        """Requests put on the wire for the device, retries included: each ended answered
        (a transaction ``ok`` or an exception reply), garbled or timed out."""
        return self.ok + self.exception_count + self.timed_out + self.garbled_attempts

    @property
    def timed_out(self) -> int:
        """Attempts that got no reply (a transaction retried and answered counts here too;
        never fewer than the transactions that timed out, a bus that counts no attempts)."""
        return max(self.line.timeouts if self.line else 0, self.timeouts)

    @property
    def garbled_attempts(self) -> int:
        """Attempts ended by a garbled reply (CRC error, truncated, malformed)."""
        return max(self.line.garbled if self.line else 0, self.garbled)

    @property
    def retried(self) -> int:
        """Transactions answered only by a retry (each also counted ``ok``)."""
        return self.line.retried if self.line else 0

    @property
    def idle_gap(self) -> float:
        """The silence a request to the device waits for now, beyond the 3.5 characters."""
        return self.line.gap if self.line else 0.0

    @property
    def gap_source(self) -> str:
        """learned, set, or "" (none)."""
        if not self.idle_gap or self.line is None:
            return ""
        return "learned" if self.line.gap_learned else "set"

    def p50(self) -> float | None:
        return quantile(self.latencies, 50)

    def p95(self) -> float | None:
        return quantile(self.latencies, 95)


class Charged(Protocol):
    """Who pays for bus time (``jobs.scheduler.DevicePoller``: its share of the bus)."""

    def charge(self, now: float, seconds: float) -> None: ...


class BusLoad:
    """Transactions and the share of time the bus was busy, over a sliding window, and
    who each transaction's time is charged to."""

    def __init__(self, started: float) -> None:
        self.started = started
        self.transactions = 0
        # the last transaction timed out or was garbled: for whom (None: not a device's)
        self._after_failure = False
        self._failed_by: Charged | None = None
        self._recent: deque[tuple[float, float]] = deque()  # (end time, duration)

    def add(self, end: float, duration: float, by: Charged | None = None, *,
            failed: bool = False) -> bool:
        """Count one transaction, made for ``by`` (None: not a device's, a gateway
        client's) and ``failed`` (timed out or garbled), and charge its time; True when
        the time was its own (the transaction before it did not fail).

        After a timeout or a garbled reply the bus waits for a quiet line before the
        next request, so the next transaction's time says nothing about its own device:
        it is charged to the failing device (to ``by`` when that was none's).
        """
        own = not self._after_failure
        payer = by if own or self._failed_by is None else self._failed_by
        self._after_failure, self._failed_by = failed, by if failed else None
        if payer is not None:
            payer.charge(end, duration)
        self.transactions += 1
        recent, since = self._recent, end - LOAD_WINDOW
        recent.append((end, duration))
        while recent and recent[0][0] < since:
            recent.popleft()
        return own

    def utilisation(self, now: float) -> float:
        """Busy share of the last ``LOAD_WINDOW`` seconds (or since the start), 0..1."""
        span = min(LOAD_WINDOW, now - self.started)
        if span <= 0:
            return 0.0
        busy = sum(d for end, d in self._recent if end >= now - LOAD_WINDOW)
        return min(1.0, busy / span)

    def rate(self, now: float) -> float:
        """Transactions per second over the window."""
        span = min(LOAD_WINDOW, now - self.started)
        n = sum(1 for end, _ in self._recent if end >= now - LOAD_WINDOW)
        return n / span if span > 0 else 0.0
