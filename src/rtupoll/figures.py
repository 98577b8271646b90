"""Small pure helpers for the figures every layer reports: time stamps as records write
them, percentiles, and a count with its noun (``count(1, "device")``). A neutral home
below the poller (``jobs``), the sniffer, the gateway and the outputs, which all use
them."""

from __future__ import annotations

import heapq
import math
from collections.abc import Collection
from datetime import UTC, datetime
from functools import lru_cache


@lru_cache(maxsize=64)  # the readings of one block share their time
def iso_time(t: float) -> str:
    """UTC, millisecond precision, ``Z`` suffix: sorts as text and parses everywhere.

    ``datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")`` with ``Z``,
    character for character (tests/jobs/test_figures.py), without building a datetime per
    stamp: ``t`` is rounded to the microsecond half to even, as ``fromtimestamp`` rounds
    it, and cut to the millisecond, as ``isoformat`` cuts it; the date and time to the
    second are made once a second."""
    fraction, whole = math.modf(t)
    micro = round(fraction * 1e6)
    if micro >= 1_000_000:
        micro, whole = micro - 1_000_000, whole + 1
    elif micro < 0:  # before 1970
        micro, whole = micro + 1_000_000, whole - 1
    return f"{_seconds(int(whole))}.{micro // 1000:03d}Z"


@lru_cache(maxsize=4)
def _seconds(whole: int) -> str:
    return datetime.fromtimestamp(whole, UTC).isoformat(timespec="seconds")[:-6]  # +00:00


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


def count(n: int, noun: str, plural: str = "") -> str:
    """``n`` and its noun, singular for exactly one: "1 device", "0 devices", "3 devices"
    (``plural`` where adding "s" is not the plural)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"
