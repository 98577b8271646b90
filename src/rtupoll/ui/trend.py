"""A numeric field's last minutes as a unicode sparkline, for the live table.

Each field keeps a fixed window of time bins (``BINS`` of ``BIN`` seconds: the last
five minutes), the latest value seen in each: a few hundred bytes per field, however
long the table runs. The line is scaled between the window's lowest and highest value;
a bin with no reading (the device was not read then) is a space, and a value that did
not move is a flat line in the middle.
"""

from __future__ import annotations

import math
from collections import deque

BLOCKS = "▁▂▃▄▅▆▇█"
BINS = 20  # characters
BIN = 15.0  # seconds each covers: 20 x 15 s = the last 5 minutes


class Trend:
    """One field's recent values, binned by time."""

    def __init__(self, bins: int = BINS, seconds: float = BIN) -> None:
        self.bins, self.seconds = bins, seconds
        self._values: deque[tuple[int, float]] = deque(maxlen=bins)  # (bin number, value)

    def add(self, t: float, value: float) -> None:
        """A reading taken at ``t`` (seconds; any clock, the same one ``line`` is given)."""
        if not math.isfinite(value):
            return
        b = int(t // self.seconds)
        if self._values and self._values[-1][0] >= b:
            if self._values[-1][0] == b:
                self._values[-1] = (b, value)  # the bin shows its latest value
            return  # an older reading than the last one: the window does not go back
        self._values.append((b, value))

    def line(self, now: float) -> str:
        """The sparkline ending at ``now``; "" until there are two readings."""
        last = int(now // self.seconds)
        seen = {b: v for b, v in self._values if last - self.bins < b <= last}
        if len(seen) < 2:
            return ""
        lo, hi = min(seen.values()), max(seen.values())
        out = []
        for b in range(last - self.bins + 1, last + 1):
            if b not in seen:
                out.append(" ")
            elif hi == lo:
                out.append(BLOCKS[len(BLOCKS) // 2 - 1])
            else:
                out.append(BLOCKS[round((seen[b] - lo) / (hi - lo) * (len(BLOCKS) - 1))])
        return "".join(out)
