"""``model.record.iso_time``: the one spelling of a time in records, character for character
what ``datetime`` spells (rounded to the microsecond half to even, cut to the
millisecond), without a datetime per stamp."""

from __future__ import annotations

from datetime import UTC, datetime

from hypothesis import example, given
from hypothesis import strategies as st

from rtupoll.model.record import iso_time


def _datetime_spelling(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds").replace(
        "+00:00", "Z")


@given(st.floats(min_value=0, max_value=4_102_444_800))  # to 2100
@example(1_700_000_000.0)
@example(1_700_000_000.9995)  # the millisecond cut, not rounded
@example(1_700_000_000.9999996)  # rounds up to the next second
@example(1_700_000_000.0000005)  # half a microsecond: to even
@example(1_699_999_999.999_999_5)
@example(0.0)
def test_a_stamp_is_datetimes_spelling(t: float) -> None:
    assert iso_time.__wrapped__(t) == _datetime_spelling(t)
    assert iso_time(t) == _datetime_spelling(t)


def test_stamps_a_second_apart_and_across_midnight() -> None:
    start = 1_704_067_199.5  # 2023-12-31T23:59:59.500Z
    for k in range(2000):
        t = start + k * 0.0007
        assert iso_time(t) == _datetime_spelling(t)
    assert iso_time(start + 0.5) == "2024-01-01T00:00:00.000Z"
