"""What the poll benchmarks share: a simulator in its own process, the plan's wire limit.

The simulator runs as ``rtupoll simulate --baud N`` in a separate process, so the
poller's figures (time, CPU) are its own and the two do not share a GIL. The
poller under test is the real one: ``rtupoll.jobs.scheduler.Scheduler`` over
``rtupoll.io.bus.Bus`` (pymodbus) on the simulator's pty.
"""

from __future__ import annotations

import contextlib
import json
import resource
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from rtupoll.config.site import DeviceConfig, Site, from_specs
from rtupoll.model.planner import plan
from rtupoll.rtu import Framing, read_frame_sizes, transaction_wire_time

SEEDS = ("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
         "banner-ez-array@5")


@contextlib.contextmanager
def simulator(baud: int | None, devices: Sequence[str] = SEEDS, *, faults: Sequence[str] = (),
              turnaround: float | None = 0.0) -> Iterator[str]:
    """``rtupoll simulate`` in a child process; yields the pty path (a stable link)."""
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "bus"
        cmd = [sys.executable, "-m", "rtupoll", "simulate", "--link", str(link), "--tick", "0",
               *devices]
        if baud:
            cmd += ["--baud", str(baud)]
        if turnaround is not None:
            cmd += ["--turnaround", str(turnaround)]
        for f in faults:
            cmd += ["--fault", f]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 15
            while not link.exists():
                if proc.poll() is not None or time.monotonic() > deadline:
                    err = proc.stderr.read().decode() if proc.stderr else ""
                    raise SystemExit(f"the simulator did not start: {err.strip()}")
                time.sleep(0.05)
            yield str(link)
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()


def seed_site(port: str, baud: int, devices: Sequence[str] = SEEDS, *,
              interval: float = 0.0) -> Site:
    """The devices on one bus at ``baud`` (the simulator serves any device at any speed)."""
    specs = [(d.rpartition("@")[0], int(d.rpartition("@")[2])) for d in devices]
    return from_specs(port, specs, baudrate=baud, interval=interval, check_serial=False)


def wire_limit(device: DeviceConfig, framing: Framing) -> float:
    """The least time one scan of ``device`` holds the bus: its plan's transactions on the
    wire (both frames and two 3.5-character silences each), no turnaround, no CPU."""
    total = 0.0
    for block in plan(device.fields, device.profile):
        request, response = read_frame_sizes(block.count, coils=not block.table.is_register)
        total += transaction_wire_time(framing, request, response)
    return total


def cpu_seconds() -> float:
    """This process's CPU time, user + system (the simulator is another process), at
    the kernel's resolution (``os.times`` counts whole clock ticks)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def transactions_of(site: Site) -> Callable[[list[str]], int]:
    """How many transactions the ``poll --format json`` records of ``site`` cost: each
    device's complete cycles (records / its fields) times its planned block reads."""
    from rtupoll.jobs.scheduler import Scheduler

    blocks = {d.config.name: len(d.blocks)
              for d in Scheduler(site, open_bus=lambda config: None).pollers()}
    fields = {d.name: len(d.fields) for _, d in site.devices()}

    def transactions(lines: list[str]) -> int:
        per_device: dict[str, int] = {}
        for line in lines:
            name = json.loads(line)["device"]
            per_device[name] = per_device.get(name, 0) + 1
        return sum(n // fields[d] * blocks[d] for d, n in per_device.items())

    return transactions
