"""How long to wait for a device's reply, learned from how long it takes.

A fixed timeout is a guess that is wrong both ways: too short and a slow device
flaps between online and timeouts, too long and a dead device (or an empty address)
costs the whole timeout every time it is asked. The bus already measures every
answer, so each device's timeout is derived from its own **reply times**: from the
end of the request on the wire to the first byte of the reply (``rtu.line``), wire
time excluded, since the bus adds the frames' wire time to any timeout itself.

The rules (``TimeoutEstimator``, pure, times as arguments):

- the start is the profile's ``limits.timeout`` (the manual's word);
- the target is a high percentile (``QUANTILE``) of the last ``WINDOW`` reply times
  times ``MARGIN``, never below the floor: ``FLOOR`` plus the 3.5-character silence
  plus the USB adapter's latency timer (``io.latency.latency_timer``), never above
  the ceiling (``CEILING``, or the site file's ``timeout_ceiling:`` / ``--timeout-ceiling``);
- **up at once**: a reply slower than the timeout allows for raises it straight to
  ``MARGIN`` times that reply time; a **late reply** (heard after its request timed
  out: a read's ``Evidence``, or the line's count between two reads,
  ``BusLike.unit_counts``) raises it to ``MARGIN`` times the late reply's time, and at
  least ``LATE_GROWTH`` times what it was;
- **down slowly**: towards a lower target by ``DOWN`` of the difference per answer,
  so one fast spell does not undo what a slow one taught;
- a timeout alone teaches nothing (the device may be gone): a dead device keeps the
  short timeout it had learned, so probing it costs little;
- a pinned timeout (``--timeout``, site file ``timeout:``) is used as given;
- a learned timeout shorter than the profile's does not shorten how long a late reply
  is still expected (``DeviceTiming.patience``, passed with each read: ``rtu.line``'s
  late window): waiting less must never mean mistaking a late reply for the next answer.

``DeviceTiming`` is one device's: ``before`` gives the next read's timeout, ``patience``
goes with the read, and ``learn`` takes the read's evidence (``rtu.transaction.Evidence``,
in the read's ``ReadResult`` or its bus error).
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rtupoll.errors import UsageError
from rtupoll.percentiles import nearest_rank

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike
    from rtupoll.rtu.line import UnitCounts
    from rtupoll.rtu.transaction import Evidence

FLOOR = 0.02  # seconds: never wait less than this beyond the wire time and the silence
CEILING = 3.0  # seconds: never learn a timeout longer than this (unless pinned)
MARGIN = 2.0  # timeout = MARGIN x the slow end of the reply times
QUANTILE = 99  # percent: "the slow end"
WINDOW = 128  # reply times kept
DOWN = 0.05  # per answer, the share of the way down to a lower target
LATE_GROWTH = 2.0  # a late reply at least multiplies the timeout by this


@dataclass
class TimeoutEstimator:
    """One device's timeout: starts at ``start``, learns from reply times (module docstring)."""

    start: float
    floor: float = FLOOR
    ceiling: float = CEILING
    samples: deque[float] = field(default_factory=lambda: deque(maxlen=WINDOW))
    _sorted: list[float] = field(default_factory=list, init=False, repr=False)  # samples, sorted
    # (samples, the index of the slow end among them): the rank, once per window size
    _rank: tuple[int, int] = field(default=(0, 0), init=False, repr=False)
    learned: bool = False  # some evidence has moved it from the start
    late_replies: int = 0
    current: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.floor <= self.ceiling:
            raise UsageError(f"timeout floor {self.floor:g} s and ceiling {self.ceiling:g} s "
                             "make no sense")
        self.current = self._clamp(self.start)

    def _clamp(self, t: float) -> float:
        return min(self.ceiling, max(self.floor, t))

    @property
    def timeout(self) -> float:
        return self.current

    def target(self) -> float | None:
        """What the reply times alone call for (None before any)."""
        if not self._sorted:
            return None
        slow = self._sorted[nearest_rank(len(self._sorted), QUANTILE) - 1]  # = quantile(samples)
        return self._clamp(MARGIN * slow)

    def _sample(self, reply_time: float) -> None:
        """Into the window; kept sorted as well, so the slow end is a lookup per answer."""
        if len(self.samples) == self.samples.maxlen:
            del self._sorted[bisect.bisect_left(self._sorted, self.samples[0])]
        self.samples.append(reply_time)
        bisect.insort(self._sorted, reply_time)

    def answered(self, reply_time: float) -> None:
        """An answer (or an exception reply) came ``reply_time`` s after the request."""
        self._sample(max(0.0, reply_time))
        self.learned = True
        ranked = self._sorted  # target(), inline: this runs once per transaction
        if len(ranked) != self._rank[0]:
            self._rank = (len(ranked), nearest_rank(len(ranked), QUANTILE) - 1)
        target = min(self.ceiling, max(self.floor, MARGIN * ranked[self._rank[1]]))
        if MARGIN * reply_time > self.current:  # slower than allowed for: up at once
            self.current = self._clamp(MARGIN * reply_time)
        elif target >= self.current:
            self.current = target
        else:
            self.current = max(target, self.current - DOWN * (self.current - target))

    def late(self, reply_time: float | None) -> None:
        """A reply came after its request had timed out (``reply_time`` if known)."""
        self.late_replies += 1
        self.learned = True
        grown = self.current * LATE_GROWTH
        if reply_time is not None:
            self._sample(reply_time)
            grown = max(grown, MARGIN * reply_time)
        self.current = self._clamp(max(self.current, grown))

    def set_floor(self, floor: float) -> None:
        """A new floor (the adapter's latency became known); the timeout respects it."""
        self.floor = min(floor, self.ceiling)
        self.current = self._clamp(self.current)


class DeviceTiming:
    """One polled device's timeout, learned from its reads' evidence.

    ``pinned``: the user's timeout (None: learn). ``before`` is called before each
    transaction and gives the timeout to use (taking late replies the line heard since
    the last read into account); the read goes with ``patience``; ``learn`` takes the
    read's ``Evidence``.
    """

    def __init__(self, start: float, *, silence: float, ceiling: float | None = None,
                 pinned: float | None = None) -> None:
        self.silence = silence
        self.pinned = pinned
        self.estimator = TimeoutEstimator(start, floor=FLOOR + silence,
                                          ceiling=CEILING if ceiling is None else ceiling)
        self._late_seen: int | None = None  # the line's count of late replies, as last seen
        self._bounds: tuple[float, float] | None = None  # (floor, ceiling) last applied
        self.counts: UnitCounts | None = None  # the line's live count of the unit's attempts

    @property
    def timeout(self) -> float:
        return self.pinned if self.pinned is not None else self.estimator.timeout

    @property
    def source(self) -> str:
        """pinned (the user's), profile (not learned yet) or learned."""
        if self.pinned is not None:
            return "pinned"
        return "learned" if self.estimator.learned else "profile"

    def before(self, bus: BusLike | None, unit: int, *, pinned: float | None = None,
               ceiling: float | None = None) -> float:
        """The timeout for the next transaction to ``unit`` on ``bus`` (``pinned``,
        ``ceiling``: the device's configuration now, which a reload may change). A late
        reply the line heard since the last read (while another device's request was
        out: ``BusLike.unit_counts``, a live view, no copy) raises it first."""
        self.pinned = pinned
        est = self.estimator
        top = CEILING if ceiling is None else ceiling
        if bus is None:
            est.ceiling, self._bounds = top, None
            return self.timeout
        bounds = (FLOOR + self.silence + bus.adapter_latency, top)
        counts = self.counts
        if bounds != self._bounds or counts is None:  # the first time, a reload, the
            counts = self.counts = bus.unit_counts(unit)  # adapter's latency known
            est.ceiling = top
            est.set_floor(bounds[0])
            self._bounds = bounds
        late = counts.late
        if late != self._late_seen:  # a late reply came (or the first time)
            self._take_late(late, counts.late_reply_time)
        return self.timeout

    @property
    def patience(self) -> float:
        """How long a late reply is still expected (passed with each read): as long as
        the manual allows, even when the timeout learned is shorter."""
        start, timeout = self.estimator.start, self.timeout
        return start if start > timeout else timeout

    def learn(self, evidence: Evidence | None) -> None:
        """A read's evidence (None: its bus told none): an answer's reply time (data or
        an exception reply), and late replies heard."""
        if evidence is None:
            return
        if evidence.reply_time is not None:
            self.estimator.answered(evidence.reply_time)
        if evidence.late != self._late_seen:
            self._take_late(evidence.late, evidence.late_reply_time)

    def _take_late(self, n: int, reply_time: float | None) -> None:
        if self._late_seen is None:
            self._late_seen = n
        if n > self._late_seen:
            self._late_seen = n
            self.estimator.late(reply_time)


def late_margin(margin: float, late_reply: float | None, ceiling: float = CEILING) -> float:
    """How long to wait when asking again an address whose answer came late (``scan``):
    ``MARGIN`` times the late reply's time, at least ``LATE_GROWTH`` times ``margin``."""
    longer = LATE_GROWTH * margin
    if late_reply is not None:
        longer = max(longer, MARGIN * late_reply)
    return min(ceiling, longer)
