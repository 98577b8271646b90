"""Cumulative histograms of times kept in rolling windows, for Prometheus.

``DeviceStats.latencies`` and a gateway client's ``waits`` are rolling windows (deques
with a maximum length): a histogram counts every value once, so it takes in only what
was appended since it last looked, recognised by object identity (a full window that
rolled on is read correctly). Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field


def appended(window: Sequence[float], last: object) -> list[float]:
    """The values appended to ``window`` after the object ``last``, oldest first (all of
    them when ``last`` is no longer in it, or None)."""
    new: list[float] = []
    for x in reversed(window):
        if x is last:
            break
        new.append(x)
    new.reverse()
    return new


@dataclass
class Histogram:
    """Prometheus buckets (``le`` bounds, cumulative), count and sum."""

    bounds: tuple[float, ...]
    counts: list[int] = field(default_factory=list)
    total: int = 0
    sum: float = 0.0
    last: object = None  # the newest value of the window taken in (by identity)

    def __post_init__(self) -> None:
        self.counts = self.counts or [0] * len(self.bounds)

    def observe(self, value: float) -> None:
        for i, bound in enumerate(self.bounds):
            if value <= bound:
                self.counts[i] += 1
        self.total += 1
        self.sum += value

    def catch_up(self, window: Sequence[float]) -> None:
        """Observe what was appended to ``window`` since the last call."""
        for x in appended(window, self.last):
            self.observe(x)
        if window:
            self.last = window[-1]

    def buckets(self) -> list[tuple[str, float]]:
        """``(le, cumulative count)`` pairs, ``+Inf`` last (``HistogramMetricFamily``)."""
        return [*((repr(float(b)), float(n)) for b, n in zip(self.bounds, self.counts,
                                                            strict=True)),
                ("+Inf", float(self.total))]
