"""The dashboard in a real browser: how soon a reading is on the page, and what an update
costs the page, for the demo and for 100 devices of 23 fields.

``rtupoll poll --simulate --http`` polls simulated devices (untimed lines: the poller
and the page are what is measured); the distribution's headless chromium opens the page
(selenium) and is left to run. The page keeps its own timings (``window.rtupollPerf`` in
``static/app.js``): for every device event, the seconds from the reading (the time the
poller stamped on it when the reply came) to the page updated (``Date.now()`` after the
card was rewritten), and the milliseconds the update took. Both clocks are this machine's.

    --devices demo      the five seed devices on two lines, 1 s interval (the default)
    --devices 100       epever-tracer@1..100 (23 fields each) on one 115200-baud line

Run: .venv/bin/python benchmarks/web_browser.py [--devices demo|100] [--seconds 30]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # its helpers' own imports
from tests.web_helpers import chromium, running


def quantile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q / 100 * len(xs)))]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", default="demo")
    ap.add_argument("--seconds", type=float, default=30.0)
    args = ap.parse_args()
    devices = [] if args.devices == "demo" else \
        [f"epever-tracer@{i}" for i in range(1, int(args.devices) + 1)]
    with tempfile.TemporaryDirectory() as tmp, running(
            ["poll", "--simulate", "--format", "json", "--http", "127.0.0.1:0", *devices],
            Path(tmp)) as p, chromium() as driver:
        driver.get(p.url)
        time.sleep(3)  # the first snapshot drawn
        driver.execute_script("rtupollPerf.latency.length = 0; rtupollPerf.update.length = 0;"
                              "rtupollPerf.events = 0;")
        cpu0 = _cpu(p.proc.pid)
        time.sleep(args.seconds)
        perf = driver.execute_script("return rtupollPerf")
        cpu = _cpu(p.proc.pid) - cpu0
        n = driver.execute_script("return document.querySelectorAll('.device').length")
        fields = driver.execute_script("return document.querySelectorAll('tr.field').length")
    lat, upd = perf["latency"], perf["update"]
    events = perf["events"]
    print(f"{n} devices, {fields} fields on the page; {events} device events in "
          f"{args.seconds:g} s ({events / args.seconds:.1f}/s; the last {len(lat)} timed); "
          f"poller CPU "
          f"{cpu / args.seconds * 100:.0f} %")
    print(f"reading -> page: p50 {quantile(lat, 50) * 1000:.0f} ms, p95 "
          f"{quantile(lat, 95) * 1000:.0f} ms, max {max(lat) * 1000:.0f} ms")
    print(f"update in the page: p50 {quantile(upd, 50):.2f} ms, p95 {quantile(upd, 95):.2f} "
          f"ms, mean {statistics.fmean(upd):.2f} ms per device event")


def _cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    main()
