"""The dashboard's trend rings: one point per step, at most an hour, in order, bounded
(rtupoll.web.trend)."""

from __future__ import annotations

import sys

import pytest

from rtupoll.web.trend import BYTES_PER_FIELD, POINTS, SPAN, STEP, Trend, TrendStore


def test_a_ring_keeps_one_point_per_step_and_at_most_an_hour_of_steps() -> None:
    store = TrendStore(1000.0)
    t = 1000.0
    for i in range(3 * POINTS):  # three hours of readings every second
        store.add("d", "f", t + i, float(i))
    ring = store.rings[("d", "f")]
    assert len(ring) == POINTS  # bounded, whatever came
    assert ring.nbytes() == BYTES_PER_FIELD == POINTS * 8
    now = t + 3 * POINTS - 1
    got = store.series("d", "f", now)
    assert len(got["t"]) == len(got["v"]) == POINTS
    assert got["t"] == sorted(got["t"]) and got["t"][-1] == now
    assert got["t"][0] >= now - SPAN - 0.05  # the last hour, nothing older
    assert all(b - a == pytest.approx(STEP) for a, b in zip(got["t"], got["t"][1:],
                                                             strict=False))
    assert got["v"][-1] == 3 * POINTS - 1  # the newest reading of the last step


def test_points_older_than_the_span_are_not_shown_and_odd_values_are_not_kept() -> None:
    store = TrendStore(0.0)
    store.add("d", "f", 10.0, 1.5)
    store.add("d", "f", 5000.0, 2.25)
    assert store.series("d", "f", 5000.0) == {"t": [5000.0], "v": [2.25]}
    assert not store.add("d", "f", 5002.0, float("nan"))
    assert not store.add("d", "f", 5002.0, 1e39)  # beyond a float32
    assert store.series("d", "f", 5002.0)["v"] == [2.25]
    assert store.series("d", "nothing", 5000.0) == {"t": [], "v": []}


def test_values_come_back_as_the_shortest_decimal_of_their_float32() -> None:
    store = TrendStore(0.0)
    for i, v in enumerate((21.5, 0.036, 296.15, 1175.0, -3.3)):
        store.add("d", "f", 10.0 * i, v)
    assert store.series("d", "f", 40.0)["v"] == [21.5, 0.036, 296.15, 1175.0, -3.3]


def test_steps_are_wall_clock_steps_the_same_for_every_store() -> None:
    a, b = TrendStore(1001.3), TrendStore(997.7)
    for s in (a, b):
        for t in (1002.1, 1003.9, 1004.2, 1005.5):
            s.add("d", "f", t, t)
    assert a.series("d", "f", 1006.0) == b.series("d", "f", 1006.0) == {
        "t": [1003.9, 1005.5], "v": [1003.9, 1005.5]}


def test_forget_drops_the_rings_of_devices_that_left() -> None:
    store = TrendStore(0.0)
    store.add("a", "f", 1.0, 1.0)
    store.add("b", "f", 1.0, 1.0)
    store.forget({"a"})
    assert list(store.rings) == [("a", "f")]


def test_memory_per_field_is_what_the_docs_say() -> None:
    ring = Trend()
    for i in range(POINTS * 2):
        ring.add(i * 20, 1.0)
    arrays = sys.getsizeof(ring.times) + sys.getsizeof(ring.values)
    assert BYTES_PER_FIELD == 14_400
    assert BYTES_PER_FIELD <= arrays <= BYTES_PER_FIELD + 2_000  # docs/web.md: 14.4 kB
