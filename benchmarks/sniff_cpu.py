"""The sniffer's share of a CPU on a saturated 115200-baud bus.

Two measurements:

- core, in virtual time: the sans-IO stream splitter and the per-device view
  (``rtupoll.sniff.session.Session``: splitting, pairing, decoding through the
  profiles, JSON records serialised) fed a saturated bus synthesised at 115200 baud
  (the five seed devices' default reads back to back, each frame followed by the
  3.5-character silence and nothing else), once as whole frames and once in the 1 ms
  chunks of a USB adapter with a 1 ms latency timer. CPU from ``time.process_time``
  against the seconds of bus time fed.
- command: ``rtupoll sniff --format json`` as a user runs it, on the tap of
  ``rtupoll simulate --baud 115200`` (its own process) while a raw master in this
  process keeps the bus saturated: the next request as soon as a reply is in, without
  even the 3.5-character silence a real master keeps, so the tap's stream is denser
  than a real bus allows and frames arrive glued. CPU of the sniffer from /proc,
  sampled once it listens and before it is stopped, so start-up is not counted; the
  load is given as transactions per second against the wire limit (both frames and
  two silences per transaction).

Run: .venv/bin/python benchmarks/sniff_cpu.py [--seconds 10]
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import termios
import time
import tty
from pathlib import Path
from typing import Any

from rtupoll.config.library import load_library
from rtupoll.rtu import Framing
from rtupoll.rtu.functions import Table
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.stream import Transaction
from rtupoll.sim.scenario import profile
from rtupoll.sniff.model import BusView, Known
from rtupoll.sniff.session import Session
from rtupoll.ui.records import to_json

BAUD = 115200
# (profile, unit, table, wire address, count): the seed devices' default reads
READS = (("net-irnet-pro", 1, Table.INPUT, 0x0006, 2), ("radar-level", 2, Table.HOLDING, 0, 1),
         ("huiwen-aq", 3, Table.INPUT, 30006, 4), ("co2meter-an117", 4, Table.INPUT, 1, 1),
         ("banner-ez-array", 5, Table.INPUT, 30001, 2))


def saturated(seconds: float, framing: Framing) -> list[tuple[bytes, float, float]]:
    """(frame, start, end) for ``seconds`` of back-to-back transactions."""
    out: list[tuple[bytes, float, float]] = []
    t, i = 0.0, 0
    while t < seconds:
        _, unit, table, address, count = READS[i % len(READS)]
        fc = table.read_function
        for frame in (ReadRequest(unit, table.read_function, address, count).frame(),
                      ReadReply(unit, fc, tuple([(i * 7 + k) & 0x7FFF
                                                 for k in range(count)])).frame()):
            end = t + framing.wire_time(len(frame))
            out.append((frame, t, end))
            t = end + framing.silence
        i += 1
    return out


def chunked(frames: list[tuple[bytes, float, float]], framing: Framing, tick: float | None
            ) -> list[tuple[bytes, float]]:
    """Whole frames (``tick`` None), or what an adapter hands over every ``tick`` s."""
    if tick is None:
        return [(f, end) for f, _, end in frames]
    out: list[tuple[bytes, float]] = []
    pending, due = bytearray(), tick
    for frame, start, _ in frames:
        for k, byte in enumerate(frame):
            at = start + (k + 1) * framing.char_time
            while at > due:
                if pending:
                    out.append((bytes(pending), due))
                    pending.clear()
                due += tick
            pending.append(byte)
    if pending:
        out.append((bytes(pending), due))
    return out


def core(seconds: float, tick: float | None) -> tuple[float, int]:
    """(CPU share, transactions) of the session on ``seconds`` of saturated bus time."""
    framing = Framing(BAUD)
    chunks = chunked(saturated(seconds, framing), framing, tick)
    known = [Known(f"{pid}@{unit}", profile(pid), unit) for pid, unit, *_ in READS]
    view = BusView(known, list(load_library().profiles.values()))
    sink_out: list[str] = []

    def sink(tx: Transaction, records: list[dict[str, Any]]) -> None:
        sink_out.extend(to_json(r) for r in records)
        if len(sink_out) > 1000:
            sink_out.clear()

    session = Session(framing, view, sink)
    cpu0 = time.process_time()
    session.run(chunks)
    session.close()
    cpu = time.process_time() - cpu0
    return cpu / seconds, view.transactions


def proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def command(seconds: float) -> tuple[float, float, float]:
    """(CPU share of the sniffer process, load against the wire limit, transactions/s)."""
    framing = Framing(BAUD)
    with tempfile.TemporaryDirectory() as tmp:
        link, tap = Path(tmp) / "bus", Path(tmp) / "tap"
        sim = subprocess.Popen([sys.executable, "-m", "rtupoll", "simulate", "--baud",
                                str(BAUD), "--turnaround", "0", "--tick", "0", "--link",
                                str(link), "--tap", str(tap),
                                *(f"{pid}@{unit}" for pid, unit, *_ in READS)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        sniffer: subprocess.Popen[bytes] | None = None
        try:
            deadline = time.monotonic() + 15
            while not tap.exists():
                if sim.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("the simulator did not start")
                time.sleep(0.05)
            sniffer = subprocess.Popen(
                [sys.executable, "-m", "rtupoll", "sniff", "-p", str(tap), "-b", str(BAUD),
                 "--format", "json", *(f"{pid}@{unit}" for pid, unit, *_ in READS)],
                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            assert sniffer.stderr is not None
            sniffer.stderr.readline()  # listening
            fd = os.open(str(link), os.O_RDWR | os.O_NOCTTY)
            tty.setraw(fd)
            attrs = termios.tcgetattr(fd)
            attrs[4] = attrs[5] = termios.B115200
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
            cpu0, t0 = proc_cpu(sniffer.pid), time.monotonic()
            wire_bytes, count, i = 0, 0, 0
            while time.monotonic() - t0 < seconds:
                _, unit, table, address, n = READS[i % len(READS)]
                i += 1
                request = ReadRequest(unit, table.read_function, address, n).frame()
                os.write(fd, request)
                want, got = 5 + 2 * n, b""
                while len(got) < want:
                    ready, _, _ = select.select([fd], [], [], 0.2)
                    if not ready:
                        break
                    got += os.read(fd, 256)
                wire_bytes += len(request) + len(got)
                count += 1  # the next request at once: denser than a real master may go
            wall = time.monotonic() - t0
            cpu = proc_cpu(sniffer.pid) - cpu0
            os.close(fd)
            busy = (framing.wire_time(wire_bytes) + 2 * count * framing.silence) / wall
            return cpu / wall, busy, count / wall
        finally:
            for p in (sniffer, sim):
                if p is not None:
                    p.send_signal(signal.SIGINT)
                    try:
                        p.wait(timeout=10)
                    except subprocess.TimeoutExpired:
                        p.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    args = ap.parse_args()
    results = {}
    limit = 0.0
    for name, tick in (("frames", None), ("1 ms chunks", 0.001)):
        bus_seconds = args.seconds * 6
        share, n = core(bus_seconds, tick)
        limit = n / bus_seconds
        results[f"core, {name}"] = {"cpu_share": round(share, 4), "transactions_s": round(limit, 1),
                                    "us_per_transaction": round(share / limit * 1e6, 1)}
        print(f"core ({name}): {share:.1%} of one CPU for a saturated {BAUD} bus "
              f"({limit:.0f} transactions/s, {share / limit * 1e6:.0f} us each)")
    share, busy, rate = command(args.seconds)
    results["command"] = {"cpu_share": round(share, 4), "load": round(busy, 3),
                          "transactions_s": round(rate, 1)}
    print(f"rtupoll sniff --format json: {share:.1%} of one CPU at {rate:.0f} transactions/s "
          f"({busy:.0%} of the wire limit of {limit:.0f}/s)")
    print(json.dumps(results))


if __name__ == "__main__":
    main()
