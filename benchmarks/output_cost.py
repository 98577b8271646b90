"""CPU per reading of the Prometheus and Influx outputs, against ``--format json``.

Two measurements, each with JSON as the yardstick in the same run:

- outputs alone: one batch of real readings (the scheduler polling the simulator, every
  field of the three 115200-baud seed devices) replayed through each output in this
  process, CPU from ``time.process_time``: the JSON writer, the Influx writer, and the
  metrics collector (its per-cycle update, and a ``/metrics`` scrape amortised over the
  readings between two scrapes at a 15 s scrape interval and a 1 s poll interval);
- the command: ``rtupoll poll --interval 0`` on a saturated 115200-baud simulated bus,
  as ``--format json``, ``--format influx`` and ``--format json --metrics`` (scraped over
  HTTP every second), CPU of the child process (``/proc/PID/stat``) per reading written,
  over the same seconds of steady polling (start-up and a warm-up second left out).

Run: .venv/bin/python benchmarks/output_cost.py [--seconds 8] [--cycles 300]
"""

from __future__ import annotations

import argparse
import asyncio
import io
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from poll_common import seed_site, simulator
from prometheus_client import CollectorRegistry, generate_latest

from rtupoll.app.poll import record_format
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.outputs.metrics import SchedulerCollector
from rtupoll.ui.record_writer import RecordWriter

DEVICES = ("radar-level@2", "huiwen-aq@3", "co2meter-an117@4")
BAUD = 115200
SCRAPE_EVERY = 15.0  # seconds, Prometheus's usual scrape interval
POLL_EVERY = 1.0  # seconds, the default poll interval


async def gather(port: str, cycles: int) -> tuple[Scheduler, list[tuple[DevicePoller,
                                                                         list[Reading]]]]:
    scheduler = Scheduler(seed_site(port, BAUD, DEVICES))
    got: list[tuple[DevicePoller, list[Reading]]] = []
    await scheduler.open()
    try:
        while len(got) < cycles:
            await scheduler.scan_once(lambda d, r: got.append((d, r)))
    finally:
        await scheduler.close()
    return scheduler, got


def alone(port: str, cycles: int, repeat: int = 5) -> None:
    scheduler, got = asyncio.run(gather(port, cycles))
    readings = sum(len(r) for _, r in got)

    def cpu(run: object) -> float:
        best = float("inf")
        for _ in range(repeat):
            t0 = time.process_time()
            run()  # type: ignore[operator]
            best = min(best, time.process_time() - t0)
        return best / readings

    def write(fmt: str) -> None:
        w = RecordWriter(io.StringIO(), record_format(fmt, scheduler.site))
        for d, r in got:
            w.write(r, d.stats.state.value)

    collector = SchedulerCollector(scheduler)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    bus = scheduler.buses[0]

    def observe() -> None:
        for d, r in got:
            collector.observe(bus, d, r)

    json_cost = cpu(lambda: write("json"))
    influx_cost = cpu(lambda: write("influx"))
    observe_cost = cpu(observe)
    t0 = time.process_time()
    n = 50
    for _ in range(n):
        body = generate_latest(registry)
    scrape = (time.process_time() - t0) / n
    per_scrape = sum(len(d.config.fields) for d in scheduler.pollers()) * SCRAPE_EVERY / POLL_EVERY
    metrics_cost = observe_cost + scrape / per_scrape
    print(f"outputs alone, {readings} readings ({len(got)} device cycles), best of {repeat}:")
    print(f"  json    {1e6 * json_cost:6.2f} µs per reading  (x1.00)")
    print(f"  influx  {1e6 * influx_cost:6.2f} µs per reading  (x{influx_cost / json_cost:.2f})")
    print(f"  metrics {1e6 * metrics_cost:6.2f} µs per reading  (x{metrics_cost / json_cost:.2f}): "
          f"update {1e6 * observe_cost:.2f} µs + one scrape {1e3 * scrape:.2f} ms "
          f"({len(body)} bytes) per {per_scrape:.0f} readings")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def proc_cpu(pid: int) -> float:
    """CPU seconds (user + system) a running process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def count(text: str, fmt: str) -> int:
    """Readings in whole lines of ``text``: JSON lines, or the fields each Influx status
    line counts."""
    text = text[:text.rfind("\n") + 1]
    if fmt == "json":
        return text.count("\n")
    n = 0
    for line in text.splitlines():
        if line.startswith("rtupoll_status,"):
            fields = dict(kv.split("=", 1) for kv in line.split(" ")[1].split(","))
            n += int(fields["ok"][:-1]) + int(fields["failed"][:-1])
    return n


def command(port: str, seconds: float, fmt: str, metrics: bool) -> tuple[float, int, int]:
    """(child CPU seconds, readings written, scrapes) of one ``rtupoll poll`` run, over
    ``seconds`` of steady polling (after start-up and one second of warm-up)."""
    listen = free_port()
    args = [sys.executable, "-m", "rtupoll", "poll", "--port", port, "--baudrate", str(BAUD),
            "--interval", "0", "--format", fmt, *DEVICES]
    if metrics:
        args += ["--metrics", f"127.0.0.1:{listen}"]
    scrapes = 0
    done = threading.Event()

    def scraper() -> None:
        nonlocal scrapes
        while not done.wait(1.0):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{listen}/metrics", timeout=2) as r:
                    r.read()
                scrapes += 1
            except OSError:
                pass

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        with out.open("w") as fh:
            proc = subprocess.Popen(args, stdout=fh, stderr=subprocess.PIPE)
            try:
                while not out.stat().st_size:
                    if proc.poll() is not None:
                        raise SystemExit(f"rtupoll poll failed: {proc.stderr.read().decode()}"
                                         if proc.stderr else "rtupoll poll failed")
                    time.sleep(0.05)
                if metrics:
                    threading.Thread(target=scraper, daemon=True).start()
                time.sleep(1.0)
                cpu0, n0 = proc_cpu(proc.pid), count(out.read_text(), fmt)
                time.sleep(seconds)
                cpu1, n1 = proc_cpu(proc.pid), count(out.read_text(), fmt)
            finally:
                done.set()
                proc.send_signal(signal.SIGINT)
                proc.communicate(timeout=20)
    return cpu1 - cpu0, n1 - n0, scrapes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--cycles", type=int, default=300)
    args = ap.parse_args()
    with simulator(BAUD, DEVICES) as port:
        alone(port, args.cycles)
    print(f"the command, --interval 0 at {BAUD} baud, {args.seconds:g} s of steady polling each:")
    base = 0.0
    for label, fmt, metrics in (("--format json", "json", False),
                                ("--format influx", "influx", False),
                                ("--format json --metrics", "json", True)):
        with simulator(BAUD, DEVICES) as port:
            cpu, n, scrapes = command(port, args.seconds, fmt, metrics)
        per = cpu / n
        base = base or per
        extra = f", {scrapes} scrapes" if metrics else ""
        print(f"  {label:25} {n:6} readings{extra}: {1e6 * per:6.1f} µs CPU per reading "
              f"(x{per / base:.2f})")


if __name__ == "__main__":
    main()
