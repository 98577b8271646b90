"""What connected dashboards cost the poller: its CPU with no browser and with 10 event
streams open.

The simulator runs in its own process (``rtupoll simulate``, untimed, as the other poll
benchmarks do), and ``rtupoll poll -p PTY --format json --http`` polls N epever-tracer
devices (23 fields each) every second, a rate it keeps, so both phases do the same
polling work and the poller's CPU (``/proc/PID/stat``) is compared directly (and per
reading written, counted in its ``-o`` file). The benchmark alternates phases with no
client and with 10 ``/api/events`` streams, read by ``curl -N`` (a browser's
EventSource is the same HTTP stream; the page's own work is the browser's),
so a machine that gets busier or quieter affects both alike.

Run: .venv/bin/python benchmarks/web_cpu.py [--devices 40] [--phase 15] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from poll_common import simulator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # its helpers' own imports
from tests.web_helpers import running

CLIENTS = 10


def cpu(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def reader(url: str) -> subprocess.Popen[bytes]:
    """An event stream read by curl (its own process: nothing here competes with the
    poller for this process's interpreter)."""
    return subprocess.Popen(["curl", "-sN", url + "api/events"], stdout=subprocess.DEVNULL)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", type=int, default=40)
    ap.add_argument("--phase", type=float, default=15.0)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    devices = [f"epever-tracer@{i}" for i in range(1, args.devices + 1)]
    with tempfile.TemporaryDirectory() as tmp, simulator(None, devices) as port:
        records = Path(tmp) / "records.jsonl"  # a file: no pipe to hold the poller up

        def written() -> int:
            with records.open("rb") as f:
                return sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))

        with running(["poll", "-p", port, "-b", "115200", "--format", "json", "-o",
                      str(records), "--http", "127.0.0.1:0", *devices], Path(tmp)) as p:
            time.sleep(3)  # past the start
            results: dict[int, list[tuple[float, int]]] = {0: [], CLIENTS: []}
            for _ in range(args.rounds):
                for clients in (0, CLIENTS):
                    streams = [reader(p.url) for _ in range(clients)]
                    time.sleep(1.0)  # connected, first snapshot sent
                    c0, r0 = cpu(p.proc.pid), written()
                    time.sleep(args.phase)
                    results[clients].append((cpu(p.proc.pid) - c0, written() - r0))
                    for s in streams:
                        s.terminate()
                        s.wait()
    per, total = {}, {}
    print(f"{args.devices} devices x 23 fields, every second; {args.rounds} phases of "
          f"{args.phase:g} s each")
    for clients, runs in results.items():
        c = sum(x for x, _ in runs)
        n = sum(y for _, y in runs)
        per[clients], total[clients] = c / n, c
        print(f"{clients:2d} event streams: {n} readings, {c:.2f} s CPU, "
              f"{c / n * 1e6:.0f} us per reading, {c / (args.phase * args.rounds) * 100:.1f} % "
              f"of a core")
    print(f"10 streams cost {(total[CLIENTS] / total[0] - 1) * 100:+.1f} % poll CPU "
          f"({(per[CLIENTS] / per[0] - 1) * 100:+.1f} % per reading)")


if __name__ == "__main__":
    main()
