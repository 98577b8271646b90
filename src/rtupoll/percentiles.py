"""Percentiles by nearest rank, the one rule every percentile rtupoll reports uses:
reply times (a device's, the bus's, the sniffer's), the gateway's clients, the timeouts
learned from reply times."""

from __future__ import annotations

import heapq
from collections.abc import Collection


def quantile(data: Collection[float], q: float) -> float | None:
    """Nearest-rank percentile (q in 0..100), None without data."""
    if not data:
        return None
    rank = nearest_rank(len(data), q)
    top = len(data) - rank + 1  # it is the top-th largest: for the slow end, 1 or 2
    if top <= 4:
        return heapq.nlargest(top, data)[-1]
    return sorted(data)[rank - 1]


def nearest_rank(n: int, q: float) -> int:
    """The nearest rank (1-based, in ascending order) of the q-th percentile of n values."""
    return int(max(1, -(-n * q // 100)))
