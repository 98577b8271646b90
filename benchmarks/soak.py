"""A soak run: does a long-running ``rtupoll poll`` grow?

    .venv/bin/python benchmarks/soak.py [--minutes 30] [--warmup 5] [--sample 60]

One real ``rtupoll poll`` process with everything on, polling three simulated devices
on one 9600-baud line (``rtupoll simulate`` in a process of its own, so that only
rtupoll is measured) with faults (CRC errors, a slow reply now and then, a device that
is dead for a stretch of requests), publishing to a local mosquitto (``--mqtt``), a
Modbus TCP gateway (``--serve``) that clients keep connecting to and leaving (a raw
socket every second: a few reads, sometimes a refused write, sometimes a client that
leaves with its request on the line), ``/metrics`` scraped every 5 s, and records
appended to a file (``-o``). Every ``--sample`` seconds it reads the process's RSS
(``/proc/PID/status`` VmRSS) and its open files (``/proc/PID/fd``), and prints a line.

At the end: RSS and open files at the end of the warm-up and at the end, the growth,
and the verdict against the bar (after warm-up, RSS grows by at most 1 MB and the
open files do not grow).
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

DEVICES = ["huiwen-aq@3", "radar-level@2", "net-irnet-pro@1"]
FAULTS = ["3:crc@5%", "2:slow=0.4@3%", "1:dead@200-260", "1:dead@900-960"]
RSS_BAR_KB = 1024
TRACED = """
import sys, threading, time, tracemalloc
tracemalloc.start(10)
def watch():
    first = None
    while True:
        time.sleep({every})
        snap = tracemalloc.take_snapshot().filter_traces(
            [tracemalloc.Filter(False, tracemalloc.__file__)])
        if first is None:
            first = snap
            continue
        with open("{out}", "a") as fh:
            fh.write(f"--- {{time.strftime('%H:%M:%S')}}\\n")
            for stat in snap.compare_to(first, "traceback")[:25]:
                fh.write(f"{{stat}}\\n" + "".join(f"    {{line}}\\n"
                                                  for line in stat.traceback.format()[-6:]))
threading.Thread(target=watch, daemon=True).start()
from rtupoll.cli import main
sys.argv[0] = "rtupoll"
sys.exit(main())
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def wait_port(port: int, proc: subprocess.Popen[bytes], what: str) -> None:
    deadline = time.monotonic() + 60
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"{what} did not listen") from None
            time.sleep(0.1)


def client(port: int, rng: random.Random) -> None:
    """One gateway client: connects, asks a few things, leaves (sometimes mid-request)."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
            for tid in range(rng.randint(1, 4)):
                unit, pdu = rng.choice([
                    (3, bytes.fromhex("04 75 36 00 04")),  # a read
                    (2, bytes.fromhex("03 00 00 00 02")),
                    (2, bytes.fromhex("06 03 F4 00 09")),  # the address register: refused
                    (254, bytes.fromhex("03 00 00 00 01")),  # a reserved unit: refused
                    (9, bytes.fromhex("03 00 00 00 01")),  # nobody there: 0x0B
                ])
                s.sendall(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
                if rng.random() < 0.1:
                    return  # leaves with its request on the line
                s.recv(300)
    except OSError:
        pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30)
    ap.add_argument("--warmup", type=float, default=5, help="minutes")
    ap.add_argument("--sample", type=float, default=60, help="seconds between samples")
    ap.add_argument("--trace", action="store_true",
                    help="run rtupoll under tracemalloc; at each sample write where memory "
                         "grew since the first (top 25 lines) to trace.txt in the run's "
                         "directory (slower; for finding a leak, not for the figures)")
    args = ap.parse_args()
    # stopped early (Ctrl-C, kill, even when started in the background): clean up
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    work = Path(tempfile.mkdtemp(prefix="rtupoll-soak-"))
    mqtt, gw, metrics = free_port(), free_port(), free_port()
    broker = subprocess.Popen([mosquitto, "-p", str(mqtt)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    wait_port(mqtt, broker, "mosquitto")
    sub = subprocess.Popen(["mosquitto_sub", "-h", "127.0.0.1", "-p", str(mqtt), "-t", "#"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run = ["-c", TRACED.format(out=work / "trace.txt", every=args.sample)] if args.trace \
        else ["-m", "rtupoll"]
    line = work / "line"  # the simulator in a process of its own: only rtupoll is measured
    simulator = subprocess.Popen([sys.executable, "-m", "rtupoll", "simulate", *DEVICES,
                                  "--baud", "9600", "--link", str(line),
                                  *(x for f in FAULTS for x in ("--fault", f))],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not line.exists():
        if simulator.poll() is not None or time.monotonic() > deadline:
            raise SystemExit("the simulator did not start")
        time.sleep(0.1)
    argv = [sys.executable, *run, "poll", "-p", str(line), "-b", "9600", *DEVICES,
            "--interval", "0.5",
            "--format", "json", "-o", str(work / "readings.jsonl"),
            "--mqtt", f"mqtt://127.0.0.1:{mqtt}", "--serve", f"127.0.0.1:{gw}",
            "--metrics", f"127.0.0.1:{metrics}"]
    err = (work / "stderr").open("wb")
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err)
    rng = random.Random(7)
    samples: list[tuple[float, int, int]] = []
    try:
        wait_port(gw, proc, "rtupoll's gateway")
        wait_port(metrics, proc, "rtupoll's /metrics")
        start = time.monotonic()
        next_sample, next_scrape = start, start
        print(f"soak: pid {proc.pid}, {args.minutes:g} min, files in {work}", flush=True)
        print(f"{'min':>6} {'RSS MB':>8} {'fds':>5}", flush=True)
        while (now := time.monotonic()) - start < args.minutes * 60:
            if proc.poll() is not None:
                raise SystemExit(f"rtupoll exited {proc.returncode}: "
                                 f"{(work / 'stderr').read_text()[-2000:]}")
            if now >= next_sample:
                samples.append(((now - start) / 60, rss_kb(proc.pid), fds(proc.pid)))
                m, r, f = samples[-1]
                print(f"{m:6.1f} {r / 1024:8.2f} {f:5d}", flush=True)
                next_sample += args.sample
            if now >= next_scrape:
                with urllib.request.urlopen(f"http://127.0.0.1:{metrics}/metrics",
                                            timeout=5) as r:
                    r.read()
                next_scrape += 5
            client(gw, rng)
            time.sleep(1.0)
        samples.append(((time.monotonic() - start) / 60, rss_kb(proc.pid), fds(proc.pid)))
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        for p in (simulator, sub, broker):
            p.terminate()
            p.wait(timeout=10)
    warm = [s for s in samples if s[0] >= args.warmup]
    if len(warm) < 2:
        raise SystemExit("too short a run for a verdict")
    (m0, r0, f0), (m1, r1, f1) = warm[0], warm[-1]
    peak = max(r for _, r, _ in warm)
    lines = (work / "readings.jsonl").read_text().count("\n")
    print(f"after warm-up ({m0:.1f} -> {m1:.1f} min): RSS {r0 / 1024:.2f} -> {r1 / 1024:.2f} MB "
          f"({(r1 - r0) / 1024:+.2f} MB, peak {peak / 1024:.2f}), open files {f0} -> {f1}; "
          f"{lines} records written; rtupoll exit {proc.returncode}")
    ok = r1 - r0 <= RSS_BAR_KB and f1 <= f0
    print("verdict: " + ("holds" if ok else "FAILS") + " (RSS growth <= 1 MB, no fd growth)")


if __name__ == "__main__":
    main()
