"""CPU per transaction, and the poller's share of a CPU, on a saturated 115200-baud bus.

The three seed devices that can run at 115200 baud (radar, Huiwen, CO2Meter) are
polled as fast as the bus allows (interval 0) against the simulator in its own
process with wire timing (turnaround 0, so the bus is as busy as it can be). Five
measurements, each over the same number of seconds:

- core: the scheduler, bus and pymodbus in this process (readings decoded, not
  written), CPU from ``getrusage`` over the polling only;
- bus: the same reads as a bare ``Bus.read`` loop, which is the scheduler's own cost
  by difference;
- peer: a bare pymodbus async client (``AsyncModbusSerialClient``) reading the same
  blocks in a loop, no silence, no resynchronisation, no decoding;
- quiet: the same client keeping the spec's 3.5-character silence before each request
  (``asyncio.sleep``), as rtupoll does. Waiting costs CPU: on a virtual machine each
  sleep and wake-up costs about as much as a transaction's own work, so this is the
  peer that does what rtupoll's bus must do;
- command: ``rtupoll poll --format json`` as a user runs it, records to a file, CPU of
  the child process in steady state (from its 100th record on; start-up is paid once
  per process) from /proc, as a ratio to the peer.

The five run in rounds against one simulator, in a different order each round, and
the figures are the medians over the rounds: CPU time on a shared virtual machine
drifts by tens of percent from one minute to the next, and interleaving keeps that
drift out of the ratios.

Run: .venv/bin/python benchmarks/poll_cpu.py [--baud 115200] [--seconds 5] [--rounds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from poll_common import cpu_seconds, seed_site, simulator, transactions_of

from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.rtu import Framing

DEVICES = ("radar-level@2", "huiwen-aq@3", "co2meter-an117@4")


async def core(port: str, baud: int, seconds: float) -> tuple[float, float, int, float]:
    """(cpu seconds, wall seconds, transactions, bus utilisation)."""
    scheduler = Scheduler(seed_site(port, baud, DEVICES))
    stop = asyncio.Event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        pass

    await scheduler.open()
    try:
        await scheduler.scan_once(sink)  # warm-up
        bus = scheduler.buses[0]
        tx0, cpu0, wall0 = bus.load.transactions, cpu_seconds(), time.monotonic()
        task = asyncio.create_task(scheduler.run(sink, stop))
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(task), seconds)
        stop.set()
        await task
        cpu, wall = cpu_seconds() - cpu0, time.monotonic() - wall0
        busy = bus.load.utilisation(time.monotonic())
        return cpu, wall, bus.load.transactions - tx0, busy
    finally:
        await scheduler.close()


async def bare(port: str, baud: int, seconds: float) -> tuple[float, float, int]:
    """The same plan's reads straight through ``Bus.read``, no scheduler: (cpu, wall, tx)."""
    scheduler = Scheduler(seed_site(port, baud, DEVICES))
    await scheduler.open()
    try:
        bus = scheduler.buses[0].transport
        reads = [(d.config, b) for d in scheduler.pollers() for b in d.blocks]
        cpu0, wall0, tx = cpu_seconds(), time.monotonic(), 0
        while time.monotonic() - wall0 < seconds:
            for dev, b in reads:
                await bus.read(dev.address, b.table, b.address, b.count,
                               timeout=dev.response_timeout)
                tx += 1
        return cpu_seconds() - cpu0, time.monotonic() - wall0, tx
    finally:
        await scheduler.close()


async def bare_pymodbus(port: str, baud: int, seconds: float, silence: float = 0.0
                        ) -> tuple[float, float, int]:
    """The peer: a plain pymodbus async RTU client reading the same blocks in a loop
    (no resync, no decoding; ``silence``: sleep that long before each request, as the
    spec's inter-frame silence asks and pymodbus does not): (cpu, wall, transactions)."""
    from pymodbus.client import AsyncModbusSerialClient

    site = seed_site(port, baud, DEVICES)
    reads = [(d.config.address, b) for d in Scheduler(site, open_bus=_no_bus).pollers()
             for b in d.blocks]
    client = AsyncModbusSerialClient(port, baudrate=baud, timeout=1, retries=0)
    await client.connect()
    calls = {"holding": client.read_holding_registers, "input": client.read_input_registers,
             "coil": client.read_coils, "discrete": client.read_discrete_inputs}
    try:
        cpu0, wall0, tx = cpu_seconds(), time.monotonic(), 0
        while time.monotonic() - wall0 < seconds:
            for unit, b in reads:
                if silence:
                    await asyncio.sleep(silence)
                reply = await calls[b.table.value](b.address, count=b.count, device_id=unit)
                assert not reply.isError()
                tx += 1
        return cpu_seconds() - cpu0, time.monotonic() - wall0, tx
    finally:
        client.close()


def command(port: str, baud: int, seconds: float, source: str | None = None
            ) -> tuple[float, float, int]:
    """(cpu seconds, wall seconds, transactions) of the real command, JSON to a file,
    in steady state: measured from its first hundred records on (start-up, paid once
    per process, is left out), CPU from /proc/PID/stat. ``source``: run rtupoll from
    that source tree instead (``--baseline``: another version, in the same rounds)."""
    site = seed_site(port, baud, DEVICES)
    transactions = transactions_of(site)

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "readings.jsonl"
        with out.open("w") as fh:
            env = dict(os.environ)
            if source is not None:
                env["PYTHONPATH"] = source
            proc = subprocess.Popen(
                [sys.executable, "-m", "rtupoll", "poll", "--port", port, "--baudrate",
                 str(baud), "--interval", "0", "--format", "json", *DEVICES],
                stdout=fh, stderr=subprocess.PIPE, env=env)
            deadline = time.monotonic() + 30
            while len(out.read_text().splitlines()) < 100:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("rtupoll poll did not start polling")
                time.sleep(0.05)
            cpu0, wall0 = _proc_cpu(proc.pid), time.monotonic()
            lines0 = out.read_text().splitlines()
            time.sleep(seconds)
            cpu1, wall1 = _proc_cpu(proc.pid), time.monotonic()
            lines1 = out.read_text().splitlines()
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=10)
            if proc.returncode:
                raise SystemExit(f"rtupoll poll failed: {err.decode().strip()}")
    return cpu1 - cpu0, wall1 - wall0, transactions(lines1) - transactions(lines0)


def _proc_cpu(pid: int) -> float:
    """User + system CPU seconds of a running process."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _no_bus(config: object) -> object:
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--seconds", type=float, default=5.0, help="per measurement")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--baseline", metavar="SRC",
                    help="also run the command from this source tree (another version's "
                         "src/, e.g. from 'git archive'), in the same rounds")
    args = ap.parse_args()
    names = {"peer": "peer: a bare pymodbus async client over the same blocks",
             "quiet": "peer keeping the silence: the same, asyncio.sleep(t3.5) before each",
             "bus": "bare Bus.read loop (line discipline + pymodbus as transport)",
             "core": "scheduler + bus (readings decoded, not written)",
             "command": "command 'rtupoll poll --format json', steady state"}
    if args.baseline:
        names["baseline"] = f"the same command from {args.baseline}"
    per_tx: dict[str, list[float]] = {name: [] for name in names}
    rates: dict[str, list[float]] = {name: [] for name in names}
    busy: list[float] = []
    with simulator(args.baud, DEVICES) as port:
        for r in range(args.rounds):
            order = list(names)[r % len(names):] + list(names)[:r % len(names)]
            for name in order:
                if name == "core":
                    cpu, wall, tx, used = asyncio.run(core(port, args.baud, args.seconds))
                    busy.append(used)
                elif name == "bus":
                    cpu, wall, tx = asyncio.run(bare(port, args.baud, args.seconds))
                elif name in ("peer", "quiet"):
                    silence = Framing(args.baud).silence if name == "quiet" else 0.0
                    cpu, wall, tx = asyncio.run(bare_pymodbus(port, args.baud, args.seconds,
                                                              silence))
                elif name == "baseline":
                    cpu, wall, tx = command(port, args.baud, args.seconds, args.baseline)
                else:
                    cpu, wall, tx = command(port, args.baud, args.seconds)
                per_tx[name].append(cpu / tx)
                rates[name].append(tx / wall)
            print(f"round {r + 1}: " + ", ".join(
                f"{name} {1e6 * per_tx[name][-1]:.0f} µs" for name in names), flush=True)
    print(f"\n{args.baud} baud, {args.rounds} rounds of {args.seconds:g} s each; the "
          f"scheduler's bus {statistics.median(busy):.0%} busy; medians, and the ratios to "
          "the two peers (in brackets: the median of the rounds' ratios, and their range):")
    for name, what in names.items():
        cost = statistics.median(per_tx[name])
        ratios = []
        for peer in ("peer", "quiet"):
            rounds = [c / q for c, q in zip(per_tx[name], per_tx[peer], strict=True)]
            ratios.append(f"x{cost / statistics.median(per_tx[peer]):.2f} "
                          f"(x{statistics.median(rounds):.2f}, "
                          f"x{min(rounds):.2f}-{max(rounds):.2f})")
        print(f"  {what}: {1e6 * cost:.0f} µs CPU per transaction "
              f"({statistics.median(rates[name]):.0f} transactions/s), "
              f"{ratios[0]} the bare pymodbus client, {ratios[1]} the one keeping the silence")
    if args.baseline:
        rounds = [c / b for c, b in zip(per_tx["command"], per_tx["baseline"], strict=True)]
        print("  the command against the baseline, round by round: "
              + ", ".join(f"x{x:.2f}" for x in rounds)
              + f" (median x{statistics.median(rounds):.2f})")


if __name__ == "__main__":
    main()
