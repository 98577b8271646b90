"""The dashboard under hostile clients: memory and a normal client's latency.

Starts ``rtupoll poll --simulate --http`` (the demo), measures its RSS and the latency of
``GET /api/state`` (a normal client, a new connection each time) alone, then with N
connections that each sent half a request and nothing more (slowloris), held open, and
again after they were closed at their header deadline. With ``--cap`` above N every
one of them is held (the worst case for memory); with the default cap (256) the rest are
refused at once (a 503).

With ``--soak SECONDS`` (and the default limits) it runs a soak instead: beside a
normal client (``GET /api/state`` every 0.1 s) 100 slow lorises (half a request, then a
byte a second, each reconnecting when it is closed), 5 clients that pipeline requests
and never read, and 10 malformed requests a second; it prints the RSS every minute, its
growth after the first, the normal client's p50/p95 against the same client alone, and
how much stderr grew; ``--calm`` runs the same without the hostile clients, for the
process's own growth (the trend rings fill for an hour).

Run: .venv/bin/python benchmarks/web_hostile.py [--hostile 1000] [--cap 2000]
     [--header-timeout 20] [--requests 200]
     .venv/bin/python benchmarks/web_hostile.py --soak 300
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

from rtupoll.percentiles import quantile

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
    ap.add_argument("--soak", type=float, default=0.0, metavar="SECONDS")
    ap.add_argument("--calm", action="store_true",
                    help="--soak without the hostile clients: the process's own growth")
    args = ap.parse_args()
    with tempfile.NamedTemporaryFile("w+", suffix=".stderr") as err:
        (soak if args.soak else run)(args, err)


def launch(err: IO[str], *options: str) -> tuple[subprocess.Popen[bytes], int]:
    proc = subprocess.Popen([sys.executable, "-m", "rtupoll", "poll", "--simulate",
                             "--format", "json", "--log-format", "text",
                             "--http", "127.0.0.1:0", *options],
                            stdout=subprocess.DEVNULL, stderr=err)
    for _ in range(600):
        err.seek(0)
        if m := re.search(r"on http://127\.0\.0\.1:(\d+)/", err.read()):
            return proc, int(m.group(1))
        time.sleep(0.1)
    proc.kill()
    raise SystemExit("the dashboard did not start")


def soak(args: argparse.Namespace, err: IO[str]) -> None:
    import threading

    proc, port = launch(err)
    stop = threading.Event()

    def normal(out: list[float], seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not stop.is_set():
            out.extend(latencies(port, 1))
            time.sleep(0.1)

    def lorises() -> None:
        socks: list[socket.socket | None] = [None] * 100
        while not stop.is_set():
            for i, s in enumerate(socks):
                try:
                    if s is None:
                        s = socks[i] = socket.create_connection(("127.0.0.1", port), 30)
                        s.setblocking(False)
                        s.send(HALF)
                    else:
                        s.send(b"x")
                except OSError:
                    if s is not None:
                        s.close()
                    socks[i] = None
            stop.wait(1.0)
        for s in socks:
            if s is not None:
                s.close()

    def readers() -> None:
        pipelined = (b"GET /static/app.js HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n") * 400
        socks: list[socket.socket | None] = [None] * 5
        while not stop.is_set():
            for i, s in enumerate(socks):
                try:
                    if s is None:
                        s = socks[i] = socket.socket()
                        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                        s.connect(("127.0.0.1", port))
                        s.sendall(pipelined)
                        s.setblocking(False)
                    elif s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0] != 1:
                        raise ConnectionResetError  # no longer established: reset
                except BlockingIOError:
                    pass
                except OSError:
                    if s is not None:
                        s.close()
                    socks[i] = None
            stop.wait(1.0)
        for s in socks:
            if s is not None:
                s.close()

    def malformed() -> None:
        while not stop.is_set():
            try:
                with socket.create_connection(("127.0.0.1", port), 30) as s:
                    s.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
                    while s.recv(65536):
                        pass
            except OSError:
                pass
            stop.wait(0.1)

    try:
        latencies(port, 50)  # warm up
        alone: list[float] = []
        normal(alone, 30)
        err.seek(0, os.SEEK_END)
        before = err.tell()
        threads = [] if args.calm else [
            threading.Thread(target=f, daemon=True) for f in (lorises, readers, malformed)]
        for t in threads:
            t.start()
        beside: list[float] = []
        client = threading.Thread(target=normal, args=(beside, args.soak), daemon=True)
        client.start()
        began = time.monotonic()
        rss_at: list[tuple[float, float]] = []
        while client.is_alive():
            client.join(60)
            rss_at.append((time.monotonic() - began, rss(proc.pid)))
            print(f"{rss_at[-1][0]:5.0f} s  RSS {rss_at[-1][1]:6.1f} MB  "
                  f"fds {len(os.listdir(f'/proc/{proc.pid}/fd'))}", flush=True)
        stop.set()
        for t in threads:
            t.join(30)
        err.seek(before)
        grew = err.read()
        first = next((m for t, m in rss_at if t >= 59), rss_at[0][1])
        a50, a95 = quantile(alone, 50) or 0.0, quantile(alone, 95) or 0.0
        b50, b95 = quantile(beside, 50) or 0.0, quantile(beside, 95) or 0.0
        print(f"RSS after the first minute {first:.1f} MB, at the end {rss_at[-1][1]:.1f} MB "
              f"(+{rss_at[-1][1] - first:.2f} MB)")
        print(f"normal client alone: p50 {a50 * 1e3:.2f} ms p95 {a95 * 1e3:.2f} ms "
              f"({len(alone)} requests); beside the hostile ones: p50 {b50 * 1e3:.2f} ms "
              f"p95 {b95 * 1e3:.2f} ms ({len(beside)}), x{b95 / a95:.2f} at p95")
        print(f"stderr grew by {len(grew)} bytes, {grew.count(chr(10))} lines")
        print(grew[-1500:])
    finally:
        stop.set()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


def run(args: argparse.Namespace, err: IO[str]) -> None:
    proc, port = launch(err, "--http-max-connections", str(args.cap),
                       "--http-header-timeout", str(args.header_timeout))
    try:
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
