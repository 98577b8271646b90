"""The dashboard under hostile clients: memory and a normal client's latency.

Starts ``rtupoll poll --simulate --http`` (the demo), measures its RSS and the latency of
``GET /api/state`` (a normal client, a new connection each time) alone, then with N
connections that each sent half a request and nothing more (slowloris), held open, and
again after they were closed at their header deadline. With ``--cap`` above N every
one of them is held (the worst case for memory); with the default cap (256) the rest are
refused at once (a 503).

Run: .venv/bin/python benchmarks/web_hostile.py [--hostile 1000] [--cap 2000]
     [--header-timeout 20] [--requests 200]
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from typing import IO

from rtupoll.figures import quantile

HALF = b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nUser-Agent: slow"


def rss(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def latencies(port: int, n: int) -> list[float]:
    """Seconds each of ``n`` requests took to be answered 200 (a 503, refused at the
    cap, counts as no answer: the list is shorter)."""
    out = []
    request = b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
    for _ in range(n):
        t = time.perf_counter()
        with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
            s.sendall(request)
            got = b""
            while chunk := s.recv(65536):
                got += chunk
        if got.startswith(b"HTTP/1.1 503"):
            continue
        assert got.startswith(b"HTTP/1.1 200"), got[:100]
        out.append(time.perf_counter() - t)
    return out


def show(what: str, pid: int, lat: list[float], asked: int) -> None:
    p50, p95 = quantile(lat, 50) or 0.0, quantile(lat, 95) or 0.0
    print(f"{what:34} RSS {rss(pid):6.1f} MB   /api/state served {len(lat)}/{asked}, "
          f"p50 {p50 * 1e3:6.2f} ms, p95 {p95 * 1e3:6.2f} ms")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--hostile", type=int, default=1000)
    ap.add_argument("--cap", type=int, default=2000)
    ap.add_argument("--header-timeout", type=float, default=20.0)
    ap.add_argument("--requests", type=int, default=200)
    args = ap.parse_args()
    with tempfile.NamedTemporaryFile("w+", suffix=".stderr") as err:
        run(args, err)


def run(args: argparse.Namespace, err: IO[str]) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "rtupoll", "poll", "--simulate",
                             "--format", "json", "--log-format", "text",
                             "--http", "127.0.0.1:0",
                             "--http-max-connections", str(args.cap),
                             "--http-header-timeout", str(args.header_timeout)],
                            stdout=subprocess.DEVNULL, stderr=err)
    try:
        port = 0
        for _ in range(600):
            err.seek(0)
            if m := re.search(r"on http://127\.0\.0\.1:(\d+)/", err.read()):
                port = int(m.group(1))
                break
            time.sleep(0.1)
        assert port, "the dashboard did not start"
        latencies(port, args.requests)  # warm up: imports, first snapshots
        show("alone", proc.pid, latencies(port, args.requests), args.requests)
        err.seek(0, os.SEEK_END)
        before = err.tell()
        held = []
        for _ in range(args.hostile):
            s = socket.create_connection(("127.0.0.1", port), timeout=30)
            s.sendall(HALF)
            held.append(s)
        time.sleep(1)
        open_fds = len(os.listdir(f"/proc/{proc.pid}/fd"))
        show(f"{args.hostile} half-open held ({open_fds} fds)", proc.pid,
             latencies(port, args.requests), args.requests)
        start = time.monotonic()
        for s in held:
            s.settimeout(args.header_timeout + 30)
            try:
                while s.recv(65536):
                    pass
            except OSError:
                pass
            s.close()
        took = time.monotonic() - start
        show(f"after they were closed ({took:.1f} s)", proc.pid,
             latencies(port, args.requests), args.requests)
        err.seek(before)
        grew = err.read()
        print(f"stderr grew by {len(grew)} bytes, {grew.count(chr(10))} lines")
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


if __name__ == "__main__":
    main()
