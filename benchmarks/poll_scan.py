"""Full-scan time of the five seed devices against the wire limit of their plan,
and transactions per scan against one request per field.

(a) Scans the five seed devices (one bus, every device's default fields) again and
    again through the real scheduler, bus and pymodbus, against the simulator in its
    own process with wire timing, and prints the mean scan time next to the plan's
    wire limit: every planned transaction's request and reply at the baud rate plus
    two 3.5-character silences (``rtu.transaction_wire_time``). The simulator's
    device turnaround is 0 here, so what is left over is the poller's own cost.
    Efficiency = wire limit / measured (target >= 85 %).
    To tell the simulator's own timing error from the poller's, the same scan is also
    made by a bare client (os.write/select, exact silences, no pymodbus, no asyncio).
(c) Prints the transactions one scan made (counted on the bus) next to the fields
    read, i.e. what one request per field would have cost, and the wire limit of both.

Run: .venv/bin/python benchmarks/poll_scan.py [--baud 9600,115200] [--scans 10]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import select
import statistics
import time
import tty

from poll_common import seed_site, simulator, wire_limit

from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.rtu import Framing, read_frame_sizes, transaction_wire_time
from rtupoll.rtu.messages import ReadRequest


async def scans(port: str, baud: int, count: int) -> tuple[list[float], int, Scheduler]:
    scheduler = Scheduler(seed_site(port, baud))
    bad: list[Reading] = []

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        bad.extend(r for r in readings if not r.ok)

    await scheduler.open()
    times = []
    try:
        await scheduler.scan_once(sink)  # warm-up: first contact, imports, caches
        before = sum(d.stats.requests for d in scheduler.pollers())
        for _ in range(count):
            start = time.perf_counter()
            await scheduler.scan_once(sink)
            times.append(time.perf_counter() - start)
        requests = sum(d.stats.requests for d in scheduler.pollers()) - before
    finally:
        await scheduler.close()
    if bad:
        raise SystemExit(f"{len(bad)} readings failed, e.g. {bad[0].device.name} "
                         f"{bad[0].field.name}: {bad[0].error}")
    return times, requests // count, scheduler


def raw_scans(port: str, scheduler: Scheduler, framing: Framing, count: int) -> float:
    """Mean time of the same scan by a bare client (os.write/select on the pty, exact
    silences, no pymodbus, no asyncio): what the simulator itself allows."""
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    reads = [(d.config.address, b) for d in scheduler.pollers() for b in d.blocks]
    times = []
    try:
        for _ in range(count + 1):
            start = time.perf_counter()
            for unit, b in reads:
                time.sleep(framing.silence)
                os.write(fd, ReadRequest(unit, b.table.read_function, b.address, b.count).frame())
                want, got = read_frame_sizes(b.count)[1], b""
                while len(got) < want:
                    select.select([fd], [], [], 1.0)
                    got += os.read(fd, 256)
            times.append(time.perf_counter() - start)
    finally:
        os.close(fd)
    return statistics.mean(times[1:])


def run(baud: int, count: int) -> None:
    framing = Framing(baud)
    with simulator(baud) as port:
        times, per_scan, scheduler = asyncio.run(scans(port, baud, count))
        raw = raw_scans(port, scheduler, framing, count)
    devices = [d.config for d in scheduler.pollers()]
    limit = sum(wire_limit(d, framing) for d in devices)
    fields = sum(len(d.fields) for d in devices)
    per_field = sum(transaction_wire_time(framing, *read_frame_sizes(f.words))
                    for d in devices for f in d.fields)
    mean, best = statistics.mean(times), min(times)
    print(f"{baud:>6} baud: full scan of {len(devices)} devices, {fields} fields: "
          f"{1000 * mean:7.1f} ms mean, {1000 * best:7.1f} ms best over {count} scans; "
          f"wire limit {1000 * limit:7.1f} ms; efficiency {limit / mean:5.1%} "
          f"(best {limit / best:5.1%})")
    print(f"             a bare client (no pymodbus, no asyncio) scans the same simulator in "
          f"{1000 * raw:.1f} ms: {limit / raw:.1%} of the wire limit; rtupoll takes "
          f"{1000 * (mean - raw) / per_scan:.2f} ms more per transaction")
    print(f"             transactions per scan: {per_scan} planned vs {fields} with one "
          f"request per field (wire limit {1000 * per_field:.1f} ms, "
          f"x{per_field / limit:.1f} the planned scan)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baud", default="9600,115200", help="comma-separated baud rates")
    ap.add_argument("--scans", type=int, default=10, help="scans measured per baud rate")
    args = ap.parse_args()
    for baud in (int(b) for b in args.baud.split(",")):
        run(baud, args.scans)


if __name__ == "__main__":
    main()
