"""Fixed profile timeouts against learned ones, in one run: dead device, scan, flapping.

Everything runs in virtual time on ``rtupoll.sim.virtual.VirtualBus``: the simulator's
engine (the devices and their turnarounds), the real line discipline
(``rtu.line``: silence, drain after a timeout, late replies) and the real scheduler and
sweep, with a clock that jumps instead of sleeping. The figures are the model's
seconds at 9600 baud, deterministic, and each pair (fixed / learned) comes from the
same run of this script. Reply times are measured at the end of the reply frame
here (the virtual bus delivers a frame whole), so learned timeouts are a little
longer than on a real port.

1. **One dead device**: four devices polled as fast as the bus allows (interval 0);
   after a minute the Huiwen module (3) dies. The three live devices' scans in the
   next minute, with every timeout pinned to its profile's against learned ones,
   and what one probe of the dead device costs.
2. **A 1-247 scan** with five devices, one of them slow (answers in 120 ms, past the
   scan's derived timeout): each empty address waits the slowest profile's timeout
   (fixed) against rtupoll's wire-derived wait with a second, longer ask for an
   address whose answer came late (learned).
3. **Flapping**: a radar sensor (profile timeout 300 ms, one retry) one of whose
   replies in twenty takes 700 ms, for ten minutes: reads without a value, timeouts,
   flaps (leaving online) and the bus time lost to reads that got nothing.

``--wire SECONDS`` also runs scenario 1 through the real bus (pymodbus) against the
simulator in its own process on a pty at 9600 baud, for SECONDS per run after a
20 s warm-up (the device dies at its 150th request, within the warm-up).

Run: .venv/bin/python benchmarks/timing.py [--wire 30]
"""

from __future__ import annotations

import asyncio
import dataclasses
import heapq
import statistics
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager

from poll_common import seed_site

from rtupoll.config.library import load_library, load_one
from rtupoll.config.site import BusConfig, from_specs
from rtupoll.jobs.scan import Found, Setting, default_margin, presence_probes, sweep
from rtupoll.jobs.scheduler import Backoff, BusPoller, DevicePoller
from rtupoll.jobs.stats import Reading
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import Line, UnitCounts
from rtupoll.rtu.transaction import ReadResult
from rtupoll.sim.device import SimDeviceConfig as SimConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.virtual import VirtualBus, VirtualClock

BAUD = 9600


class TimedBus(VirtualBus):
    """The virtual bus, logging each read; replies due by now reach the line before the
    next request goes, as bytes would."""

    adapter_latency = 0.0
    log: list[tuple[float, bool]] | None = None  # (duration, got a value) per read

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0) -> ReadResult:
        while self._pending and self._pending[0][0] <= self._clock():
            when, _, data = heapq.heappop(self._pending)
            self.line.receive(data, when)
        start, ok = self._clock(), False
        try:
            values = await super().read(unit, table, address, count, timeout=timeout,
                                        retries=retries, patience=patience)
            ok = True
            return values
        finally:
            if self.log is not None:
                self.log.append((self._clock() - start, ok))


def pinned(config: BusConfig) -> BusConfig:
    """Every device's timeout pinned to its profile's (what a fixed-timeout poller does)."""
    return dataclasses.replace(config, devices=tuple(
        dataclasses.replace(d, timeout=d.profile.limits.timeout) for d in config.devices))


def poller(specs: Sequence[tuple[str, int]], sims: Sequence[SimConfig], *, fixed: bool,
           interval: float = 0.0) -> tuple[VirtualClock, BusPoller, Engine]:
    clock = VirtualClock()
    engine = Engine(list(sims), tick=None)
    bus = TimedBus(engine, Framing(BAUD), clock=clock, sleep=clock.sleep)
    config = from_specs("virtual", list(specs), baudrate=BAUD, interval=interval,
                        check_serial=False).buses[0]
    return clock, BusPoller(pinned(config) if fixed else config, bus, backoff=Backoff(),
                            clock=clock, wall=clock, rand=lambda: 0.5), engine


async def run_for(bp: BusPoller, clock: VirtualClock, seconds: float) -> list[tuple[DevicePoller,
                                                                             float, bool]]:
    """Poll for ``seconds`` of virtual time; (device, cycle time, got every field)."""
    end, out = clock.now + seconds, []
    while clock.now < end:
        dev = bp.next_device()
        clock.now = max(clock.now, dev.next_due)
        start = clock.now
        got: list[bool] = []

        def sink(d: DevicePoller, rs: list[Reading], got: list[bool] = got) -> None:
            got.append(all(r.ok for r in rs))

        await bp.run_one(dev, sink)
        out.append((dev, clock.now - start, bool(got and got[0])))
    return out


# -- 1. one dead device -------------------------------------------------------------

DEVICES = [("net-irnet-pro", 1), ("huiwen-aq", 3), ("radar-level", 4), ("co2meter-an117", 20)]
DEAD = 3


def dead_device(fixed: bool) -> tuple[int, float, float]:
    """(live devices' scans in the minute after 3 died, cost of one probe of it, its
    timeout then)."""
    sims = [SimConfig(load_one(p), a) for p, a in DEVICES]
    clock, bp, engine = poller(DEVICES, sims, fixed=fixed)

    async def go() -> tuple[int, float, float]:
        await run_for(bp, clock, 60)
        engine.device(DEAD).address = 200  # gone
        cycles = await run_for(bp, clock, 60)
        live = sum(1 for d, _, ok in cycles if d.config.address != DEAD and ok)
        probes = [t for d, t, _ in cycles if d.config.address == DEAD]
        dead = next(d for d in bp.devices if d.config.address == DEAD)
        return live, statistics.median(probes[1:] or probes), dead.timing.timeout

    return asyncio.run(go())


# -- 2. a 1-247 scan -----------------------------------------------------------------

SCAN = [("net-irnet-pro", 3), ("radar-level", 7), ("huiwen-aq", 12), ("co2meter-an117", 20),
        ("banner-ez-array", 31)]
SLOW = 12  # answers in 120 ms


def scan(fixed: bool, listen: bool = True) -> tuple[float, list[int]]:
    """(seconds, addresses identified); ``listen``: ask late answerers again."""
    profiles = sorted(load_library().profiles.values(), key=lambda p: p.id)
    sims = [SimConfig(load_one(p), a, turnaround=0.12 if a == SLOW else None) for p, a in SCAN]
    engine = Engine(sims, tick=None)
    clock = VirtualClock()
    margin = default_margin(profiles)
    if fixed:  # every empty address waits the slowest profile's timeout
        margin = max(p.limits.timeout for p in profiles)

    @asynccontextmanager
    async def open_bus(s: Setting) -> AsyncIterator[VirtualBus]:
        bus = TimedBus(engine, s.framing, clock=clock, sleep=clock.sleep) if not fixed else \
            VirtualBus(engine, s.framing, clock=clock, sleep=clock.sleep)
        if fixed or not listen:  # a fixed-timeout scan does not listen for late answers
            deaf = Line(s.framing)  # (a line that heard nothing)
            bus.unit_counts = lambda unit: UnitCounts(deaf, unit)  # type: ignore[method-assign,unused-ignore]
        yield bus

    found: list[Found] = []
    addresses = [a for a in range(1, 248) if a not in (0xCC, 0xFE)]
    asyncio.run(sweep(open_bus, [Setting(BAUD)], addresses, profiles, margin=margin,
                      probes=presence_probes(profiles), found=found))
    return clock.now, sorted(f.address for f in found if f.profile is not None)


# -- 3. flapping ---------------------------------------------------------------------


def flapping(fixed: bool) -> tuple[int, int, int, int, float, float]:
    """(reads, reads without a value, timeouts, flaps, seconds lost, bus seconds in all)
    in ten minutes.

    A flap is a change of state away from online; the time lost is the bus time of the
    reads that got no value (their timeouts, retries and the quiet after them)."""
    spec = [("radar-level", 4)]
    sims = [SimConfig(load_one("radar-level"), 4, faults=(parse_fault("4:slow=0.7@5%"),))]
    clock, bp, _ = poller(spec, sims, fixed=fixed, interval=1.0)
    bus = bp.transport
    assert isinstance(bus, TimedBus)
    log: list[tuple[float, bool]] = []
    bus.log = log

    async def go() -> tuple[int, int, int, int, float, float]:
        dev = bp.devices[0]
        flaps, was = 0, dev.stats.state
        end = clock.now + 600
        while clock.now < end:
            await run_for(bp, clock, 1e-9)
            flaps += dev.stats.state is not was and was.value == "online"
            was = dev.stats.state
        lost = sum(t for t, ok in log if not ok)
        return len(log), sum(1 for _, ok in log if not ok), dev.stats.timeouts, \
            flaps, lost, sum(t for t, _ in log)

    return asyncio.run(go())


# -- 1 again, on the wire ------------------------------------------------------------


async def wire_run(port: str, fixed: bool, warm: float, seconds: float) -> tuple[int, int]:
    """(live devices' good cycles, the dead device's cycles) in ``seconds`` after ``warm``."""
    from rtupoll.jobs.scheduler import Scheduler

    site = seed_site(port, BAUD, [f"{p}@{a}" for p, a in DEVICES])
    if fixed:
        site = dataclasses.replace(site, buses=(pinned(site.buses[0]),))
    scheduler = Scheduler(site)
    counting = False
    live, dead = 0, 0

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        nonlocal live, dead
        if counting and dev.config.address == DEAD:
            dead += 1
        elif counting and all(r.ok for r in readings):
            live += 1

    stop = asyncio.Event()
    await scheduler.open()
    try:
        task = asyncio.create_task(scheduler.run(sink, stop))
        await asyncio.sleep(warm)
        counting = True
        await asyncio.sleep(seconds)
        stop.set()
        await task
    finally:
        await scheduler.close()
    return live, dead


def on_the_wire(seconds: float) -> None:
    """Scenario 1 through the real bus (pymodbus) and the simulator on a pty at 9600."""
    from poll_common import simulator

    warm = 20.0  # the Huiwen module dies at its 150th request, within this
    print(f"\n1w. on the wire (simulator process, pty, {BAUD} baud): huiwen-aq@3 dies at its "
          f"150th request; the {seconds:g} s after {warm:g} s")
    got = {}
    for label, fixed in (("fixed", True), ("learned", False)):
        with simulator(BAUD, [f"{p}@{a}" for p, a in DEVICES], faults=(f"{DEAD}:dead@150-",),
                       turnaround=None) as port:
            got[label] = asyncio.run(wire_run(port, fixed, warm, seconds))
    (lf, df), (ll, dl) = got["fixed"], got["learned"]
    print(f"   live devices' good scans: fixed {lf}, learned {ll}: x{ll / lf:.2f}; "
          f"probes of the dead device: fixed {df}, learned {dl}")


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--wire", type=float, default=0.0, metavar="SECONDS",
                        help="also run scenario 1 on the real wire for SECONDS per run")
    args = parser.parse_args()
    print(f"virtual time, {BAUD} baud (rtupoll.sim.virtual: the simulator's engine and the "
          "real line discipline)\n")
    (lf, pf, tf), (ll, pl, tl) = dead_device(True), dead_device(False)
    print("1. one dead device (huiwen-aq@3 dies after a minute; interval 0)")
    print(f"   live devices' scans in the next minute: fixed {lf}, learned {ll}: "
          f"x{ll / lf:.2f}")
    print(f"   one probe of the dead device: fixed {pf * 1000:.0f} ms (timeout "
          f"{tf * 1000:.0f} ms), learned {pl * 1000:.0f} ms (timeout {tl * 1000:.0f} ms): "
          f"x{pl / pf:.2f}")
    (sf, ff), (sl, fl), (sd, fd) = scan(True), scan(False), scan(False, listen=False)
    print(f"\n2. scan 1-247 ({len(SCAN)} devices, one answering in 120 ms)")
    print(f"   fixed (slowest profile timeout per address): {sf:.1f} s, found {ff}")
    print(f"   learned (derived wait, late ones asked again): {sl:.1f} s, found {fl}: "
          f"x{sl / sf:.2f} of the time")
    print(f"   (the derived wait without asking again: {sd:.1f} s, found {fd})")
    fixed, learned = flapping(True), flapping(False)
    print("\n3. flapping (radar-level, profile timeout 300 ms and 1 retry, 1 reply in 20 "
          "takes 700 ms; 10 min, interval 1 s)")
    for label, (c, b, o, f, x, total) in (("fixed", fixed), ("learned", learned)):
        print(f"   {label + ':':8} {c} reads, {b} without a value, {o} timeouts, "
              f"{f} flaps, {x:.1f} s of bus time lost, {total:.0f} s of bus time in all")
    print(f"   bus time in all, learned / fixed: x{learned[5] / fixed[5]:.2f}; time lost: "
          f"{fixed[4]:.1f} s -> {learned[4]:.1f} s")
    if args.wire:
        on_the_wire(args.wire)


if __name__ == "__main__":
    main()
