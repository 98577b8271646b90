"""Small pure helpers for the figures every layer reports: time stamps as records write
them, and percentiles. A neutral home below the poller (``jobs``), the sniffer, the
gateway and the outputs, which all use them."""

from __future__ import annotations

import heapq
from collections.abc import Collection
from datetime import UTC, datetime
from functools import lru_cache


@lru_cache(maxsize=64)  # the readings of one block share their time
def iso_time(t: float) -> str:
    """UTC, millisecond precision, ``Z`` suffix: sorts as text and parses everywhere."""
    stamp = datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")
    return stamp.replace("+00:00", "Z")


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
