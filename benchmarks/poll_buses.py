"""Several saturated buses in one process: each bus's rate against the same bus alone.

``N`` simulators (``rtupoll simulate --baud 115200``, each in its own process, on a pty
of its own) serve the three seed devices that run at 115200 baud (radar, Huiwen,
CO2Meter) with no turnaround, and one ``Scheduler`` in this process polls them at
interval 0, so every bus is as busy as its wire allows. Each round polls every bus
alone for ``--seconds``, then all ``N`` together for as long; the figure is each bus's
transactions per second together divided by its own rate alone in the same round (the
goal: at least 0.95). Rounds interleave the two, so the machine's drift hits both.

``--before`` also polls them together as the previous version did, holding the event
loop for up to 2 ms of each silence however many buses share it (``io/bus.py``
``_SLEEP_SHARED`` set to ``_SLEEP_MAX`` for that run), in the same rounds.

Run: .venv/bin/python benchmarks/poll_buses.py [--buses 4] [--seconds 4] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import statistics
import time

from poll_common import cpu_seconds, seed_site, simulator

import rtupoll.io.bus as bus_module
from rtupoll.config.site import Site
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading

DEVICES = ("radar-level@2", "huiwen-aq@3", "co2meter-an117@4")
BAUD = 115200


def site_of(ports: list[str]) -> Site:
    buses = [dataclasses.replace(seed_site(port, BAUD, DEVICES).buses[0], name=f"bus{i}")
             for i, port in enumerate(ports)]
    return Site(tuple(buses))


HELD = [0.0]  # seconds the buses held the event loop, waiting out a silence's end
_quiet = bus_module.Bus._quiet


def _counted_quiet(self: bus_module.Bus, delay: float) -> bool:
    start = time.perf_counter()
    try:
        return _quiet(self, delay)
    finally:
        HELD[0] += time.perf_counter() - start


bus_module.Bus._quiet = _counted_quiet  # type: ignore[method-assign]


async def rates(ports: list[str], seconds: float) -> tuple[list[float], float, float]:
    """Each bus's transactions per second over ``seconds`` of saturated polling, this
    process's CPU seconds per transaction, and the share of the time the event loop was
    held waiting out the end of a silence (``Bus._quiet``)."""
    scheduler = Scheduler(site_of(ports))
    stop = asyncio.Event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        pass

    await scheduler.open()
    try:
        await scheduler.scan_once(sink)  # warm-up
        before = [bp.load.transactions for bp in scheduler.buses]
        cpu0, wall0, held0 = cpu_seconds(), time.monotonic(), HELD[0]
        task = asyncio.create_task(scheduler.run(sink, stop))
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(asyncio.shield(task), seconds)
        done = [bp.load.transactions - b for bp, b in zip(scheduler.buses, before, strict=True)]
        cpu, wall = cpu_seconds() - cpu0, time.monotonic() - wall0
        held = (HELD[0] - held0) / wall
        stop.set()
        await task
        return [n / wall for n in done], cpu / max(1, sum(done)), held
    finally:
        await scheduler.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--buses", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=4.0, help="per measurement")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--before", action="store_true",
                    help="also together as the previous version held the loop")
    args = ap.parse_args()
    ratios: list[list[float]] = []  # per round, per bus
    before: list[list[float]] = []
    held: list[float] = []  # the share of the time the loop was held, together
    held_before: list[float] = []
    alone_cpu: list[float] = []
    together_cpu: list[float] = []
    with contextlib.ExitStack() as stack:
        ports = [stack.enter_context(simulator(BAUD, DEVICES)) for _ in range(args.buses)]
        for r in range(args.rounds):
            alone = []
            for port in ports:
                (rate,), cpu, _ = asyncio.run(rates([port], args.seconds))
                alone.append(rate)
                alone_cpu.append(cpu)
            together, cpu, hold = asyncio.run(rates(ports, args.seconds))
            together_cpu.append(cpu)
            held.append(hold)
            ratios.append([t / a for t, a in zip(together, alone, strict=True)])
            if args.before:
                shared, bus_module._SLEEP_SHARED = bus_module._SLEEP_SHARED, bus_module._SLEEP_MAX
                try:
                    old, _, hold = asyncio.run(rates(ports, args.seconds))
                    held_before.append(hold)
                finally:
                    bus_module._SLEEP_SHARED = shared
                before.append([t / a for t, a in zip(old, alone, strict=True)])
                print("  before: ratios " + ", ".join(f"{x:.2f}" for x in before[-1])
                      + f"; loop held {held_before[-1]:.0%}", flush=True)
            print(f"round {r + 1}: alone " + ", ".join(f"{a:.0f}" for a in alone)
                  + " /s; together " + ", ".join(f"{t:.0f}" for t in together)
                  + " /s; ratios " + ", ".join(f"{x:.2f}" for x in ratios[-1])
                  + f"; loop held {held[-1]:.0%}", flush=True)
    flat = sorted(x for row in ratios for x in row)
    per_round = [statistics.median(row) for row in ratios]
    print(f"\n{args.buses} buses at {BAUD} baud, {args.rounds} rounds of {args.seconds:g} s: "
          f"each bus's rate together / alone: min {flat[0]:.2f}, median "
          f"{statistics.median(flat):.2f}, max {flat[-1]:.2f} (rounds' medians: "
          + ", ".join(f"{x:.2f}" for x in per_round) + "); CPU per transaction alone "
          f"{1e6 * statistics.median(alone_cpu):.0f} µs, together "
          f"{1e6 * statistics.median(together_cpu):.0f} µs; the event loop held "
          f"{statistics.median(held):.0%} of the time together")
    if before:
        old = sorted(x for row in before for x in row)
        print(f"the previous version in the same rounds: min {old[0]:.2f}, median "
              f"{statistics.median(old):.2f}, max {old[-1]:.2f}; the loop held "
              f"{statistics.median(held_before):.0%} of the time")


if __name__ == "__main__":
    main()
