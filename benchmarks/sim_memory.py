"""The simulator's memory under a saturating poller, minute by minute (issue 32).

People leave ``rtupoll simulate`` running for days; its memory must stop growing after
the first minute. Three runs, each the real command in a child process whose resident
memory (VmRSS) is read from /proc once a minute:

1. ``link``: ``rtupoll simulate DEVICES --link L`` polled from this process by the real
   poller (``Scheduler`` over ``Bus``) at interval 0, replies at once: the bus saturated;
2. ``inprocess``: ``rtupoll poll --simulate DEVICES --interval 0 --format json`` (the
   simulator in the poller's process, as the issue measured it), output to /dev/null;
3. ``replay``: ``rtupoll simulate --replay CAPTURE`` for a short and a long capture
   (written here from the simulator's own replies at 115200 baud), polled the same
   way: its memory must not depend on the capture's length.

Run: .venv/bin/python benchmarks/sim_memory.py [--minutes 30] [--replay-minutes 2]
     [--capture-mb 1,20] [--runs link,inprocess,replay]

Passes (exit 0) when, in every run, growth after the first minute is at most 0.5 MB,
and the long capture's replay holds at most 5 MB more than the short one's.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from poll_common import seed_site

from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.model.planner import plan
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build
from rtupoll.sniff.capfile import CaptureWriter

DEVICES = ("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "banner-ez-array@5")
BAUD = 9600  # the line these four share (the simulator answers only at its speed)
GROWTH_LIMIT = 0.5  # MB after the first minute
REPLAY_LIMIT = 5.0  # MB more for the long capture than for the short one


def rss_mb(pid: int) -> float:
    """A process's resident memory, MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


@contextlib.contextmanager
def child(cmd: Sequence[str], ready: Path | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """A command in a child process (started when ``ready`` exists, if given)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while ready is not None and not ready.exists():
            if proc.poll() is not None or time.monotonic() > deadline:
                err = proc.stderr.read().decode() if proc.stderr else ""
                raise SystemExit(f"{' '.join(cmd)} did not start: {err.strip()}")
            time.sleep(0.05)
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Poller:
    """The real poller at interval 0 on a port, in a thread of this process."""

    def __init__(self, port: str, baud: int, devices: Sequence[str]) -> None:
        self.site = seed_site(port, baud, devices)
        self.transactions = 0
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)

    async def _main(self) -> None:
        scheduler = Scheduler(self.site)
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        self._ready.set()

        def sink(dev: DevicePoller, readings: list[Reading]) -> None:
            pass

        await scheduler.open()
        try:
            await scheduler.run(sink, self._stop)
        finally:
            self.transactions = scheduler.buses[0].load.transactions
            await scheduler.close()

    def __enter__(self) -> Poller:
        self._thread.start()
        self._ready.wait()
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None and self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=30)


def watch(pid: int, minutes: float, label: str) -> list[float]:
    """RSS at start (after 5 s of warm-up) and at the end of every minute."""
    time.sleep(5)
    samples = [rss_mb(pid)]
    print(f"  {label}: start {samples[0]:.2f} MB", flush=True)
    for m in range(1, int(minutes) + 1):
        time.sleep(60)
        samples.append(rss_mb(pid))
        print(f"  {label}: minute {m:>2} {samples[-1]:.2f} MB", flush=True)
    return samples


def growth(samples: Sequence[float]) -> float:
    """MB grown after the first minute (peak from minute 1 on, against minute 1)."""
    return max(samples[1:]) - samples[1] if len(samples) > 2 else 0.0


def run_link(minutes: float) -> list[float]:
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "bus"
        cmd = [sys.executable, "-m", "rtupoll", "simulate", "--link", str(link), *DEVICES]
        with child(cmd, link) as proc, Poller(str(link), BAUD, DEVICES) as poller:
            samples = watch(proc.pid, minutes, "link")
        print(f"  link: {poller.transactions} transactions polled", flush=True)
    return samples


def run_inprocess(minutes: float) -> list[float]:
    cmd = [sys.executable, "-m", "rtupoll", "poll", "--simulate", "--interval", "0",
           "--format", "json", *DEVICES]
    with child(cmd) as proc:
        return watch(proc.pid, minutes, "inprocess")


def write_capture(path: Path, megabytes: float, baud: int = 115200) -> int:
    """A capture of the four devices polled in turn, from the simulator's own replies,
    until the file holds ``megabytes``; returns the number of transactions."""
    framing = Framing(baud)
    engine = Engine(build(list(DEVICES)).devices, tick=1.0)
    reads = [ReadRequest(d.address, b.table.read_function, b.address, b.count).frame()
             for d in engine.devices for b in plan(d.profile.default_fields(), d.profile)]
    writer = CaptureWriter(path, framing, "/dev/ttyUSB0")
    t, n = 1_700_000_000.0, 0
    try:
        while path.stat().st_size < megabytes * 1e6:
            for request in reads:
                t += framing.wire_time(len(request))
                writer.write(request, t)
                for tx in engine.handle(request, t):
                    t += framing.silence + 0.005 + framing.wire_time(len(tx.data))
                    writer.write(tx.data, t)
                t += 2 * framing.silence
                n += 1
    finally:
        writer.close()
    return n


def run_replay(minutes: float, sizes: Sequence[float]) -> dict[float, list[float]]:
    out: dict[float, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mb in sizes:
            capture = Path(tmp) / f"bus-{mb:g}MB.pcapng"
            n = write_capture(capture, mb)
            print(f"  replay: {capture.name}, {capture.stat().st_size / 1e6:.1f} MB, "
                  f"{n} transactions", flush=True)
            link = Path(tmp) / "bus"
            cmd = [sys.executable, "-m", "rtupoll", "simulate", "--replay", str(capture),
                   "--link", str(link)]
            with child(cmd, link) as proc, Poller(str(link), 115200, DEVICES):
                out[mb] = watch(proc.pid, minutes, f"replay {mb:g} MB")
            os.unlink(capture)
    return out


def table(rows: Sequence[tuple[str, Sequence[float]]]) -> str:
    lines = ["| run | start | minute 1 | last | growth after minute 1 |", "|---|---|---|---|---|"]
    for name, s in rows:
        last = f"{s[-1]:.1f} MB (minute {len(s) - 1})"
        lines.append(f"| {name} | {s[0]:.1f} MB | {s[min(1, len(s) - 1)]:.1f} MB | {last} "
                     f"| {growth(s):+.2f} MB |")
    return "\n".join(lines)


def by_minute(rows: Sequence[tuple[str, Sequence[float]]]) -> str:
    """Every sample: a row per minute, a column per run (MB)."""
    lines = ["| minute | " + " | ".join(name for name, _ in rows) + " |",
             "|---" * (len(rows) + 1) + "|"]
    for m in range(max(len(s) for _, s in rows)):
        cells = [f"{s[m]:.2f}" if m < len(s) else "" for _, s in rows]
        lines.append(f"| {'start' if m == 0 else m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=30, help="for link and inprocess")
    ap.add_argument("--replay-minutes", type=float, default=2)
    ap.add_argument("--capture-mb", default="1,20", help="capture sizes to replay, MB")
    ap.add_argument("--runs", default="link,inprocess,replay")
    args = ap.parse_args()
    runs = set(args.runs.split(","))
    rows: list[tuple[str, list[float]]] = []
    if "link" in runs:
        rows.append(("`simulate --link`, polled from another process", run_link(args.minutes)))
    if "inprocess" in runs:
        rows.append(("`poll --simulate` (one process)", run_inprocess(args.minutes)))
    replay: dict[float, list[float]] = {}
    if "replay" in runs:
        sizes = [float(s) for s in args.capture_mb.split(",")]
        replay = run_replay(args.replay_minutes, sizes)
        rows += [(f"`simulate --replay`, {mb:g} MB capture", s) for mb, s in replay.items()]
    print(table(rows))
    print(by_minute(rows))
    ok = all(growth(s) <= GROWTH_LIMIT for _, s in rows)
    if len(replay) > 1:
        peaks = [max(s) for s in replay.values()]
        spread = max(peaks) - min(peaks)
        print(f"replay: peak {min(peaks):.1f} .. {max(peaks):.1f} MB across capture sizes "
              f"(spread {spread:.1f} MB, limit {REPLAY_LIMIT:g})")
        ok = ok and spread <= REPLAY_LIMIT
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
