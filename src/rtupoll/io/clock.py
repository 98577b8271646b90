"""The line's clock: the one source of every time on a bus -- when bytes arrived, when a
request went, a silence's end, an attempt's deadline, a reply's time, a sniffer's
arrivals. The rules (``rtupoll.rtu``) read no clock; the drivers (``io.bus``,
``io.syncbus``, ``sniff.port``) read this one.

It must tick finer than the line's characters: a 3.5-character silence is 4 ms at 9600
baud and 0.3 ms at 115200. ``time.monotonic`` does on Linux, macOS and Windows from
Python 3.13 (QueryPerformanceCounter); before 3.13 it is Windows's GetTickCount64, which
ticks every 15.6 ms, and an elapsed time read across one tick reads 15.6 ms long when
it was a few microseconds: a request would go inside the silence it is to keep
(tests/io/test_clock.py shows it in virtual time). ``time.perf_counter`` is
QueryPerformanceCounter on every Windows Python (and monotonic everywhere), so the
line takes it wherever ``time.monotonic`` is too coarse (``choose``).

The line's times are its own: a time from this clock is compared only with another
from it, never with the event loop's ``loop.time()`` (``time.monotonic``), so a timer
on the loop is set by a delay (``call_later``), not by a line time (``call_at``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

# a clock this fine or finer is fine enough: a ninth of a character at 115200 baud (87 µs)
FINE = 1e-5


def choose(monotonic_resolution: float) -> Callable[[], float]:
    """The line's clock, given ``time.monotonic``'s resolution (``time.get_clock_info``):
    ``time.monotonic`` when it is ``FINE`` enough, else ``time.perf_counter``."""
    return time.monotonic if monotonic_resolution <= FINE else time.perf_counter


now: Callable[[], float] = choose(time.get_clock_info("monotonic").resolution)
