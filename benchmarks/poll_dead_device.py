"""The live devices' scan rate with one of five devices dead, against all five alive.

Polls the five seed devices as fast as the bus allows (interval 0) through the real
scheduler, bus and pymodbus, against the simulator in its own process with wire
timing, for the same time twice: once all alive, once with the Huiwen module (3) dead.
Prints the scans the four others completed in each run and the ratio (target >= 80 %),
plus what the dead device cost: its attempts and the bus time they took.

Run: .venv/bin/python benchmarks/poll_dead_device.py [--baud 9600] [--seconds 25]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib

from poll_common import seed_site, simulator

from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading

DEAD = 3


async def poll_for(port: str, baud: int, seconds: float) -> Scheduler:
    scheduler = Scheduler(seed_site(port, baud))
    stop = asyncio.Event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        if dev.config.address != DEAD:
            bad = [r for r in readings if not r.ok]
            if bad:
                raise SystemExit(f"{dev.config.name}: {bad[0].error}")

    await scheduler.open()
    try:
        task = asyncio.create_task(scheduler.run(sink, stop))
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(task), seconds)
        stop.set()
        await task
    finally:
        await scheduler.close()
    return scheduler


def run(baud: int, seconds: float) -> None:
    results = {}
    for label, faults in (("all alive", ()), ("3 dead", (f"{DEAD}:dead",))):
        with simulator(baud, faults=faults, turnaround=None) as port:
            results[label] = asyncio.run(poll_for(port, baud, seconds))
    scans = {label: {d.config.address: d.stats.cycles for d in s.pollers()}
             for label, s in results.items()}
    live = [a for a in scans["all alive"] if a != DEAD]
    alive, dead = (sum(scans[k][a] for a in live) for k in ("all alive", "3 dead"))
    gone = next(d for d in results["3 dead"].pollers() if d.config.address == DEAD)
    print(f"{baud:>6} baud, {seconds:g} s each, interval 0: the four live devices completed "
          f"{alive} scans with all alive, {dead} with device {DEAD} dead: "
          f"{dead / alive:.0%} of the rate")
    print("             per device, alive/dead run: "
          + ", ".join(f"{a}: {scans['all alive'][a]}/{scans['3 dead'][a]}" for a in live))
    print(f"             the dead device: {gone.stats.requests} attempts in {seconds:g} s "
          f"({gone.stats.timeouts} timeouts), state {gone.stats.state.value}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baud", default="9600", help="comma-separated baud rates")
    ap.add_argument("--seconds", type=float, default=25.0, help="length of each run")
    args = ap.parse_args()
    for baud in (int(b) for b in args.baud.split(",")):
        run(baud, args.seconds)


if __name__ == "__main__":
    main()
