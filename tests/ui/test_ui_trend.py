"""The live display's trend sparkline of the last minutes (rtupoll.ui.trend)."""

from __future__ import annotations


def test_a_trend_sparkline_of_the_last_minutes() -> None:
    from rtupoll.ui.trend import BINS, BLOCKS, Trend

    t = Trend()
    assert t.line(0) == ""  # one reading is no trend
    for i, v in enumerate([10, 12, 14, 16, 18]):
        t.add(100 + 15 * i, v)
    line = t.line(100 + 15 * 4)
    assert len(line) == BINS
    assert line[-5:] == "".join(BLOCKS[round(k * 7 / 4)] for k in range(5))  # ▁▃▅▆█
    assert line[:-5] == " " * (BINS - 5)  # no readings before: blank, not zero
    flat = Trend()
    flat.add(0, 5.0)
    flat.add(20, 5.0)
    assert set(flat.line(20).strip()) == {BLOCKS[3]}  # a value that did not move
    late = t.line(100 + 15 * 4 + 15 * BINS)  # five minutes later, nothing new
    assert late == ""  # the window moved on
