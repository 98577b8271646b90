"""The last hour of every numeric field, in bounded rings (the dashboard's trend charts).

One ``Trend`` per field: two ``array`` columns, the time as a 4-byte unsigned count of
tenths of a second since the store's epoch (13 years of range) and the value as a
4-byte float (about 7 significant digits, as much as a register pair carries). At
most one point per ``STEP`` seconds is kept (steps of wall-clock time, ``t // STEP``; a
newer reading in the same step replaces the older), so ``POINTS`` points always cover at
least ``SPAN`` seconds, whatever the poll interval: a field costs at most
``BYTES_PER_FIELD`` bytes of points (14,400), plus the two arrays' headers; a field
read every 10 s fills only a fifth of that in an hour, as the columns grow to their
bound and then wrap around. The bound holds for any number of readings
(``tests/web/test_web_trend.py``; ``benchmarks/web_trends.py`` measures 2,000 fields).
"""

from __future__ import annotations

import math
from array import array

SPAN = 3600.0  # seconds a chart shows
STEP = 2.0  # seconds: at most one point per step
POINTS = int(SPAN / STEP)  # points a ring holds at most
TICK = 0.1  # seconds per unit of the stored times
STEP_TICKS = round(STEP / TICK)
BYTES_PER_FIELD = POINTS * (array("I").itemsize + array("f").itemsize)


class Trend:
    """A ring of (time, value) points of one field, oldest first when read."""

    __slots__ = ("_head", "times", "values")

    def __init__(self) -> None:
        self.times = array("I")  # ticks since the store's epoch
        self.values = array("f")
        self._head = 0  # once full: the index of the oldest point

    def add(self, tick: int, value: float) -> None:
        times = self.times
        n = len(times)
        if n:
            last = self._head - 1  # the newest point (-1: the end, until the ring wraps)
            if tick // STEP_TICKS == times[last] // STEP_TICKS:  # the same step:
                times[last], self.values[last] = tick, value  # the newer reading
                return
        if n < POINTS:
            times.append(tick)
            self.values.append(value)
        else:
            head = self._head
            times[head], self.values[head] = tick, value
            self._head = head + 1 if head + 1 < POINTS else 0

    def points(self, since: int = 0) -> tuple[list[int], list[float]]:
        """Ticks and values from ``since`` on, oldest first."""
        order = range(self._head, self._head + len(self.times))
        n = len(self.times) or 1
        ts, vs = [], []
        for i in order:
            t = self.times[i % n]
            if t >= since:
                ts.append(t)
                vs.append(self.values[i % n])
        return ts, vs

    def __len__(self) -> int:
        return len(self.times)

    def nbytes(self) -> int:
        """Bytes the points take (the arrays' buffers, without their object headers)."""
        return self.times.buffer_info()[1] * self.times.itemsize + \
            self.values.buffer_info()[1] * self.values.itemsize


class TrendStore:
    """Every field's ring, by (device, field), with one epoch for their times."""

    def __init__(self, epoch: float) -> None:
        # wall-clock seconds of tick 0, on a step boundary: the steps are the same for
        # every store (and the page's own, which it fills from the events)
        self.epoch = math.floor(epoch / STEP) * STEP
        self.rings: dict[tuple[str, str], Trend] = {}

    def tick(self, wall: float) -> int:
        return max(0, round((wall - self.epoch) / TICK))

    def wall(self, tick: int) -> float:
        return self.epoch + tick * TICK

    def add(self, device: str, field: str, wall: float, value: float) -> bool:
        """Keep a point; False (nothing kept) for a value that is no number to draw."""
        if not -3.4e38 <= value <= 3.4e38:  # NaN, infinite or beyond a float32
            return False
        ring = self.rings.get((device, field))
        if ring is None:
            ring = self.rings[(device, field)] = Trend()
        tick = round((wall - self.epoch) / TICK)
        ring.add(tick if tick > 0 else 0, value)
        return True

    def series(self, device: str, field: str, now: float) -> dict[str, list[float]]:
        """The last ``SPAN`` seconds of a field as {"t": [wall seconds], "v": [values]}."""
        ring = self.rings.get((device, field))
        if ring is None:
            return {"t": [], "v": []}
        ts, vs = ring.points(self.tick(now - SPAN))
        return {"t": [round(self.wall(t), 1) for t in ts],
                "v": [_short(v) for v in vs]}

    def forget(self, devices: set[str]) -> None:
        """Drop the rings of devices that are gone (a reload removed them)."""
        for key in [k for k in self.rings if k[0] not in devices]:
            del self.rings[key]

    def nbytes(self) -> int:
        return sum(r.nbytes() for r in self.rings.values())


def _short(v: float) -> float:
    """A float32 as the shortest decimal that reads back as it (21.5, not 21.5000000001)."""
    for digits in range(6, 10):
        s = float(f"{v:.{digits}g}")
        if array("f", [s])[0] == v:
            return s
    return v
