"""An edge soak: hostile clients beside normal ones, against one ``rtupoll poll``.

    .venv/bin/python benchmarks/edge_soak.py [--hostile-minutes 5] [--baseline 60]

One real ``rtupoll poll --simulate huiwen-aq@3 net-irnet-pro@1 --baud 9600 --serve ...
--http ... --mqtt ...`` process (the simulated line inside it, with the wire's real
time) publishing to a local mosquitto, and one ``rtupoll web --mqtt ...`` (the fleet
viewer) reading that broker, on loopback only. The hostile clients run in a process of
their own, so that their loops do not slow this one's measurements (one interpreter
lock). Three normal clients run all the time: a Modbus TCP client (one read at a time,
every 0.2 s), a dashboard client (``GET /api/state`` on one keep-alive connection, every
0.5 s) and the same against the fleet viewer; each reply's time is recorded and checked (a gateway
reply must be the read's, never an exception; a page's reply must be 200).

Phases: a baseline (``--baseline`` seconds, normal clients only), the hostile phase
(``--hostile-minutes``), then a second baseline. In the hostile phase, beside the normal
clients (each hostile client from its own loopback address, 127.0.0.2-6):

- 100 half-open HTTP connections (half a request's headers, held; each one the
  dashboard closes is opened again at once) and 100 idle ones (nothing sent);
- a gateway client that pipelines reads as fast as its socket takes them and never
  reads a reply (its receive buffer as small as the system allows);
- a disconnecting writer: every 0.5 s a new connection sends a write (FC 16, the IRNET's
  gas level) and closes at once;
- 12 gateway connections from one address (the cap per address is 8; each one closed
  is opened again every second);
- hostile retained MQTT messages, one every 2 s in turn: a 400-digit number as the
  real gateway's CO2 reading, a ``bridge/info`` whose field has ``precision``
  100000000, 400 kB on a topic no gateway owns (50 topics in turn), bad JSON.

Every 10 s it reads both processes' RSS (``/proc/PID/status`` VmRSS). At the end: the
normal clients' p50/p95 in the baselines and in the hostile phase, their ratio, the
RSS from the end of the hostile phase's first minute to its end, the counts (replies,
exceptions, refusals in the log, requests dropped unsent) and the verdict against the
bars (p95 at most 2x the baseline's, RSS growth at most 1 MB). Loops are bounded in
time; everything stops by itself.
"""

from __future__ import annotations

import argparse
import http.client
import json
import multiprocessing
import re
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

from soak import free_port, rss_kb  # (benchmarks/, run from the checkout as the others)

RSS_BAR_KB = 1024
P95_BAR = 2.0
READ = struct.pack(">BHH", 4, 0x7536, 4)  # huiwen-aq: PM2.5, TVOC, HCHO, CO2
WRITE = struct.pack(">BHHB", 16, 0x0200, 2, 4) + bytes.fromhex("0000 4248")  # IRNET gas
HALF = b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "
HANG = 30.0  # a socket wait that never comes back ends the client's loop


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def wait_port(port: int, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 60
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"rtupoll did not listen on {port}") from None
            time.sleep(0.1)


def connect(port: int, source: str, *, rcvbuf: int | None = None) -> socket.socket | None:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        if rcvbuf is not None:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        s.bind((source, 0))
        s.settimeout(5)
        s.connect(("127.0.0.1", port))
        return s
    except OSError:
        s.close()
        return None


def closed(s: socket.socket) -> bool:
    """Whether the other end has closed ``s`` (what it sent is read and dropped)."""
    try:
        s.setblocking(False)
        while True:
            data = s.recv(65536)
            if not data:
                return True
    except BlockingIOError:
        return False
    except OSError:
        return True


class Run:
    """The shared state: the phase, the stop flags, what the clients measured."""

    def __init__(self) -> None:
        self.phase = "baseline"
        self.stop = threading.Event()  # everything
        self.calm = threading.Event()  # the hostile clients
        self.times: dict[tuple[str, str], list[float]] = {}
        self.bad: dict[str, int] = {"gateway": 0, "dashboard": 0, "fleet": 0}
        self.lock = threading.Lock()
        self.hostile: dict[str, int] = {"half-open": 0, "idle": 0, "hog bytes": 0,
                                        "hog last sent at (s)": 0, "writes": 0,
                                        "over cap": 0, "mqtt": 0}

    def took(self, who: str, seconds: float) -> None:
        with self.lock:
            self.times.setdefault((who, self.phase), []).append(seconds)

    def count(self, what: str, n: int = 1) -> None:
        with self.lock:
            self.hostile[what] += n


def normal_gateway(run: Run, port: int) -> None:
    tid = 0
    s = socket.create_connection(("127.0.0.1", port), timeout=HANG)
    try:
        while not run.stop.is_set():
            tid = (tid + 1) % 65536
            start = time.monotonic()
            s.sendall(mbap(tid, 3, READ))
            got = b""
            while len(got) < 7 or len(got) < 6 + struct.unpack(">H", got[4:6])[0]:
                chunk = s.recv(512)
                if not chunk:
                    raise SystemExit("the gateway closed the normal client's connection")
                got += chunk
            run.took("gateway", time.monotonic() - start)
            if got[7] != 0x04 or struct.unpack(">H", got[:2])[0] != tid:
                run.bad["gateway"] += 1
            run.stop.wait(0.2)
    finally:
        s.close()


def normal_dashboard(run: Run, port: int, who: str = "dashboard") -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=HANG)
    try:
        while not run.stop.is_set():
            start = time.monotonic()
            conn.request("GET", "/api/state")
            reply = conn.getresponse()
            reply.read()
            run.took(who, time.monotonic() - start)
            if reply.status != 200:
                run.bad[who] += 1
            run.stop.wait(0.5)
    finally:
        conn.close()


def held(run: Run, port: int, source: str, n: int, what: str, send: bytes) -> None:
    """``n`` connections held open from ``source``; one the server closes is opened again."""
    socks: list[socket.socket] = []
    try:
        while not run.calm.is_set():
            gone = [s for s in socks if closed(s)]
            for old in gone:
                old.close()
            socks = [s for s in socks if s not in gone]
            while len(socks) < n and not run.calm.is_set():
                s = connect(port, source)
                if s is None:
                    break
                if send:
                    try:
                        s.sendall(send)
                    except OSError:
                        s.close()
                        continue
                socks.append(s)
                run.count(what)
            run.calm.wait(1.0)
    finally:
        for s in socks:
            s.close()


def hog(run: Run, port: int) -> None:
    """Pipelines reads as fast as the socket takes them; never reads a reply."""
    batch = b"".join(mbap(t, 3, READ) for t in range(64))
    s = connect(port, "127.0.0.3", rcvbuf=1)
    start = time.monotonic()
    while s is not None and not run.calm.is_set():
        s.setblocking(False)
        try:
            run.count("hog bytes", s.send(batch))
            run.hostile["hog last sent at (s)"] = round(time.monotonic() - start)
        except BlockingIOError:
            run.calm.wait(0.05)
        except OSError:
            s.close()
            s = connect(port, "127.0.0.3", rcvbuf=1)
    if s is not None:
        s.close()


def writer(run: Run, port: int) -> None:
    while not run.calm.is_set():
        s = connect(port, "127.0.0.4")
        if s is not None:
            try:
                s.sendall(mbap(1, 1, WRITE))
                run.count("writes")
            except OSError:
                pass
            s.close()
        run.calm.wait(0.5)


HOSTILE = ("half-open", "idle", "hog", "writer", "over-cap", "mqtt")
NINES = "9" * 400


def mqtt(run: Run, broker: int) -> None:
    """Hostile retained messages, one every 2 s in turn (mosquitto_pub, loopback)."""
    evil = {"gateway": "evil", "devices": {"d": {"fields": {
        "v": {"label": "v", "kind": "number", "precision": 100_000_000}}}}}
    messages = [("rtupoll/edge/huiwen-aq_3", f'{{"co2": {NINES}, "temperature": 1e999}}'),
                ("rtupoll/evil/bridge/info", json.dumps(evil)),
                ("rtupoll/evil/d", '{"v": 1.5}'), ("rtupoll/edge/huiwen-aq_3", "{not json"),
                ("elsewhere/{n}", "x" * 400_000)]
    n = 0
    while not run.calm.is_set():
        topic, payload = messages[n % len(messages)]
        subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker), "-r", "-q",
                        "1", "-t", topic.format(n=n % 50), "-s"], input=payload.encode(),
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=HANG,
                       check=False)
        run.count("mqtt")
        n += 1
        run.calm.wait(2)


def hostile(gw: int, web: int, broker: int, seconds: float,
            out: multiprocessing.Queue[dict[str, int]], only: tuple[str, ...] = HOSTILE
            ) -> None:
    """The hostile clients (``only`` those named), for ``seconds``, in a process of their
    own; their counts to ``out`` at the end."""
    run = Run()
    kinds: dict[str, tuple[Callable[..., None], tuple[object, ...]]] = {
             "half-open": (held, (web, "127.0.0.2", 100, "half-open", HALF)),
             "idle": (held, (web, "127.0.0.5", 100, "idle", b"")),
             "hog": (hog, (gw,)), "writer": (writer, (gw,)),
             "over-cap": (held, (gw, "127.0.0.6", 12, "over cap", b"")),
             "mqtt": (mqtt, (broker,))}
    threads = [threading.Thread(target=f, args=(run, *a), daemon=True)
               for f, a in (kinds[k] for k in only)]
    for t in threads:
        t.start()
    run.calm.wait(seconds)
    run.calm.set()
    for t in threads:
        t.join(timeout=HANG)
    out.put(dict(run.hostile))


Sample = tuple[float, str, dict[str, int]]  # seconds, phase, RSS (kB) by process


def sampler(run: Run, pids: dict[str, int], samples: list[Sample]) -> None:
    start = time.monotonic()
    while not run.stop.is_set():
        samples.append((time.monotonic() - start, run.phase,
                        {name: rss_kb(pid) for name, pid in pids.items()}))
        run.stop.wait(10)


def quantiles(xs: list[float]) -> tuple[float, float]:
    qs = statistics.quantiles(xs, n=100, method="inclusive")
    return qs[49], qs[94]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hostile-minutes", type=float, default=5)
    ap.add_argument("--baseline", type=float, default=60, help="seconds, before and after")
    ap.add_argument("--only", action="append", choices=HOSTILE,
                    help="only these hostile clients (repeatable; default: all), to see "
                         "what each one costs")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    work = Path(tempfile.mkdtemp(prefix="rtupoll-edge-soak-"))
    gw, web, fleet, broker = free_port(), free_port(), free_port(), free_port()
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    procs: list[subprocess.Popen[bytes]] = [subprocess.Popen(
        [mosquitto, "-p", str(broker)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    err_path, fleet_err = work / "stderr.txt", work / "fleet-stderr.txt"
    with err_path.open("wb") as err, fleet_err.open("wb") as ferr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "rtupoll", "poll", "--simulate", "huiwen-aq@3",
             "net-irnet-pro@1", "--baud", "9600", "--interval", "1", "--format", "json", "-o",
             str(work / "readings.jsonl"), "--serve", f"127.0.0.1:{gw}",
             "--http", f"127.0.0.1:{web}", "--mqtt", f"mqtt://127.0.0.1:{broker}",
             "--mqtt-id", "edge"],
            stdout=subprocess.DEVNULL, stderr=err)
        viewer = subprocess.Popen(
            [sys.executable, "-m", "rtupoll", "web", "--mqtt", f"mqtt://127.0.0.1:{broker}",
             "--http", f"127.0.0.1:{fleet}"], stdout=subprocess.DEVNULL, stderr=ferr)
    procs += [proc, viewer]
    run = Run()
    samples: list[Sample] = []
    threads: list[threading.Thread] = []

    def start(target: Callable[..., None], *a: object) -> None:
        t = threading.Thread(target=target, args=(run, *a), daemon=True)
        t.start()
        threads.append(t)

    try:
        wait_port(broker, procs[0])
        wait_port(gw, proc)
        wait_port(web, proc)
        wait_port(fleet, viewer)
        time.sleep(10)  # the first polls, the first page, the fleet's first messages
        start(sampler, {"poll": proc.pid, "web": viewer.pid}, samples)
        start(normal_gateway, gw)
        start(normal_dashboard, web)
        start(normal_dashboard, fleet, "fleet")
        print(f"baseline {args.baseline:g} s", flush=True)
        time.sleep(args.baseline)
        run.phase = "hostile, 1st minute"
        hostile_at = time.monotonic()
        print(f"hostile clients for {args.hostile_minutes:g} min", flush=True)
        counts: multiprocessing.Queue[dict[str, int]] = multiprocessing.Queue()
        child = multiprocessing.get_context("fork").Process(
            target=hostile, args=(gw, web, broker, args.hostile_minutes * 60, counts,
                                  tuple(args.only or HOSTILE)), daemon=True)
        child.start()
        while time.monotonic() - hostile_at < args.hostile_minutes * 60:
            time.sleep(10)
            if time.monotonic() - hostile_at >= 60:
                run.phase = "hostile"
            for p in procs:
                if p.poll() is not None:
                    raise SystemExit(f"{p.args!r} ended ({p.returncode}); see {work}")
            last = samples[-1][2] if samples else {}
            print(f"  {time.monotonic() - hostile_at:5.0f} s  RSS " + ", ".join(
                f"{k} {v / 1024:.1f} MB" for k, v in last.items()), flush=True)
        run.hostile = counts.get(timeout=120)
        child.join(timeout=HANG)
        samples.append((time.monotonic(), "hostile-end",
                        {"poll": rss_kb(proc.pid), "web": rss_kb(viewer.pid)}))
        run.phase = "after"
        print(f"second baseline {args.baseline:g} s", flush=True)
        time.sleep(args.baseline)
    finally:
        run.stop.set()
        run.calm.set()
        for t in threads:
            t.join(timeout=HANG)
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    report(run, samples, err_path.read_text(errors="replace"),
           fleet_err.read_text(errors="replace"), args)


def report(run: Run, samples: list[Sample], log: str, fleet_log: str,
           args: argparse.Namespace) -> None:
    ok = True
    print("\nnormal clients' reply times (ms):")
    print(f"  {'client':<10} {'phase':<18} {'n':>6} {'p50':>8} {'p95':>8}")
    for who in ("gateway", "dashboard", "fleet"):
        base = run.times.get((who, "baseline"), []) + run.times.get((who, "after"), [])
        first = run.times.get((who, "hostile, 1st minute"), [])
        later = run.times.get((who, "hostile"), [])
        rows = [("baseline (both)", base), ("hostile, 1st min", first),
                ("hostile, after", later), ("hostile, all", first + later)]
        for name, xs in rows:
            if len(xs) < 2:
                continue
            p50, p95 = quantiles(xs)
            print(f"  {who:<10} {name:<18} {len(xs):>6} {p50 * 1000:>8.1f} {p95 * 1000:>8.1f}")
        for name, xs in rows[1:]:
            if len(xs) < 2:
                continue
            ratio = quantiles(xs)[1] / quantiles(base)[1]
            print(f"  {who:<10} p95 {name} / baseline: {ratio:.2f} (bar {P95_BAR:g})")
            ok &= ratio <= P95_BAR or name != "hostile, all"
    print(f"  replies not as asked: {run.bad}")
    ok &= not any(run.bad.values())
    hostile = [(t, kb) for t, phase, kb in samples if phase.startswith("hostile,") or
               phase == "hostile"]
    end = next(kb for _, phase, kb in samples if phase == "hostile-end")
    for name in ("poll", "web"):
        minute = next((kb[name] for t, kb in hostile if t >= hostile[0][0] + 60),
                      hostile[-1][1][name])
        peak = max(kb[name] for _, kb in hostile)
        print(f"\nRSS of {name}: at the start {samples[0][2][name] / 1024:.1f} MB; hostile "
              f"phase: after its first minute {minute / 1024:.2f} MB, at its end "
              f"{end[name] / 1024:.2f} MB (peak {peak / 1024:.2f} MB): growth "
              f"{(end[name] - minute) / 1024:+.2f} MB (bar {RSS_BAR_KB / 1024:g} MB)")
        ok &= end[name] - minute <= RSS_BAR_KB
    print(f"hostile clients: {dict(run.hostile)}")
    dropped = sum(int(m) for m in re.findall(r"(\d+) requests? dropped unsent", log))
    refusals = [line for line in log.splitlines() if ": refused " in line]
    print(f"log: {len(log.splitlines())} lines, {len(log)} bytes; {dropped} gateway "
          f"requests dropped unsent; {len(refusals)} refusal lines; "
          f"{log.count('Traceback')} tracebacks")
    for line in refusals[:6]:
        print(f"  {line[:160]}")
    ok &= "Traceback" not in log
    dropped_lines = [line for line in fleet_log.splitlines() if "dropped" in line]
    print(f"fleet viewer's log: {len(fleet_log.splitlines())} lines, {len(fleet_log)} "
          f"bytes; {len(dropped_lines)} 'dropped' lines; {fleet_log.count('Traceback')} "
          "tracebacks")
    for line in dropped_lines[:3]:
        print(f"  {line[:160]}")
    ok &= "Traceback" not in fleet_log
    print(f"\n{'PASS' if ok else 'FAIL'}: hostile {args.hostile_minutes:g} min, baselines "
          f"{args.baseline:g} s each")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
