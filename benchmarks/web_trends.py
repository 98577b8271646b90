"""Memory of the dashboard's trend rings (``rtupoll.web.trend``) for many fields.

Fills one ring per field with more than an hour of readings (one a second, so every
ring is at its bound and has wrapped), and measures what the rings hold: the Python
heap they take (``tracemalloc``, everything allocated for them, dict entries and keys
included), next to the documented bound (``BYTES_PER_FIELD``, the points alone). Also
the CPU time of one ``add`` (a reading kept) and of one ``series`` (a chart opened).

Run: .venv/bin/python benchmarks/web_trends.py [--fields 2000] [--seconds 4000]
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

from rtupoll.web.trend import BYTES_PER_FIELD, POINTS, TrendStore


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fields", type=int, default=2000)
    ap.add_argument("--seconds", type=int, default=4000, help="readings per field, one a second")
    args = ap.parse_args()
    devices = max(1, args.fields // 20)
    names = [(f"device-{d}@{d % 247 + 1}", f"field_{f}") for d in range(devices)
             for f in range(args.fields // devices)]
    t0 = 1_800_000_000.0
    tracemalloc.start()
    base, _ = tracemalloc.get_traced_memory()
    store = TrendStore(t0)
    cpu = time.process_time()
    for s in range(args.seconds):
        for i, (dev, field) in enumerate(names):
            store.add(dev, field, t0 + s, float(i + s % 97))
    adds = time.process_time() - cpu
    held, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    n = len(names)
    assert all(len(r) == POINTS for r in store.rings.values())
    cpu = time.process_time()
    for dev, field in names[:200]:
        store.series(dev, field, t0 + args.seconds)
    series = (time.process_time() - cpu) / 200
    heap = held - base
    print(f"{n} fields, {args.seconds} readings each (every ring full: {POINTS} points)")
    print(f"points (documented bound): {BYTES_PER_FIELD} B/field, "
          f"{BYTES_PER_FIELD * n / 1e6:.1f} MB")
    print(f"heap held by the rings:    {heap / n:.0f} B/field, {heap / 1e6:.1f} MB")
    print(f"add: {adds / (args.seconds * n) * 1e6:.2f} us per reading; "
          f"series (a chart opened): {series * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
