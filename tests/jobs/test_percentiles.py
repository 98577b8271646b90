"""Percentiles by nearest rank (rtupoll/percentiles.py): the one rule of every percentile
rtupoll reports."""

from __future__ import annotations

import random

from rtupoll.percentiles import nearest_rank, quantile


def test_no_data_has_no_percentile() -> None:
    assert quantile([], 50) is None and quantile([], 99) is None


def test_quantile_is_the_nearest_rank_whatever_the_shortcut() -> None:
    rnd = random.Random(7)
    for n in (1, 2, 5, 99, 100, 101, 128):
        data = [rnd.random() for _ in range(n)]
        for q in (50, 90, 99, 100):
            rank = max(1, -(-n * q // 100))
            assert nearest_rank(n, q) == rank, (n, q)
            assert quantile(data, q) == sorted(data)[int(rank) - 1], (n, q)


def test_the_median_of_four_is_the_second() -> None:
    assert quantile([4, 1, 3, 2], 50) == 2 and quantile([4, 1, 3, 2], 100) == 4
