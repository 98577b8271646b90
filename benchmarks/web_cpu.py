"""What connected dashboards cost the poller: its CPU per reading with no browser and
with 10 event streams open.

``rtupoll poll --simulate --format json --http`` polls simulated devices (its records
counted from stdout); the benchmark alternates phases with no client and with 10
``/api/events`` streams, read by threads of this process (a browser's EventSource is the
same HTTP stream; the page's own work happens in the browser, not in the poller), and
compares the poller's CPU (``/proc/PID/stat``) per reading written. Phases alternate
(none, 10, none, 10, ...) so a machine that gets busier or quieter affects both alike.

    --devices demo      the five seed devices, --interval 0 (as fast as the lines go)
    --devices 100       epever-tracer@1..100 (23 fields each), 1 s interval (the default)

Run: .venv/bin/python benchmarks/web_cpu.py [--devices demo|100] [--phase 15] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

CLIENTS = 10


def cpu(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


class Counter(threading.Thread):
    def __init__(self, stream: object) -> None:
        super().__init__(daemon=True)
        self.stream, self.lines = stream, 0

    def run(self) -> None:
        for _ in self.stream:  # type: ignore[attr-defined]
            self.lines += 1


def reader(url: str, stop: threading.Event, got: list[int]) -> None:
    with urllib.request.urlopen(url + "api/events", timeout=30) as r:
        n = 0
        for line in r:
            if line.startswith(b"event: "):
                n += 1
            if stop.is_set():
                break
    got.append(n)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", default="demo")
    ap.add_argument("--phase", type=float, default=15.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    extra = ["--interval", "0"] if args.devices == "demo" else \
        [f"epever-tracer@{i}" for i in range(1, int(args.devices) + 1)]
    with tempfile.TemporaryDirectory() as tmp:
        err = Path(tmp) / "stderr"
        with err.open("w") as fh:
            proc = subprocess.Popen([sys.executable, "-m", "rtupoll", "poll", "--simulate",
                                     "--format", "json", "--http", "127.0.0.1:0", *extra],
                                    stdout=subprocess.PIPE, stderr=fh)
        counter = Counter(proc.stdout)
        counter.start()
        try:
            url = ""
            deadline = time.monotonic() + 120
            while not url and time.monotonic() < deadline:
                m = re.search(r"dashboard on (http://\S+/)", err.read_text())
                url = m.group(1) if m else ""
                time.sleep(0.1)
            assert url, err.read_text()
            time.sleep(3)  # past the start
            results: dict[int, list[tuple[float, int]]] = {0: [], CLIENTS: []}
            events = 0
            for _ in range(args.rounds):
                for clients in (0, CLIENTS):
                    stop = threading.Event()
                    got: list[int] = []
                    threads = [threading.Thread(target=reader, args=(url, stop, got),
                                                daemon=True) for _ in range(clients)]
                    for t in threads:
                        t.start()
                    time.sleep(1.0)  # connected, first snapshot sent
                    c0, r0 = cpu(proc.pid), counter.lines
                    time.sleep(args.phase)
                    results[clients].append((cpu(proc.pid) - c0, counter.lines - r0))
                    stop.set()
                    for t in threads:
                        t.join(timeout=30)
                    events += sum(got)
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=60)
    per = {}
    for clients, runs in results.items():
        c = sum(x for x, _ in runs)
        n = sum(y for _, y in runs)
        per[clients] = c / n
        print(f"{clients:2d} event streams: {n} readings, {c:.2f} s CPU, "
              f"{c / n * 1e6:.0f} us per reading, {c / (args.phase * args.rounds) * 100:.0f} % "
              f"of a core")
    print(f"10 streams cost {(per[CLIENTS] / per[0] - 1) * 100:+.1f} % CPU per reading "
          f"({events} events delivered)")


if __name__ == "__main__":
    main()
