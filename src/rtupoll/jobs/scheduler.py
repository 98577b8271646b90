"""When each device is read: intervals, backoff, resuming, and several buses at once.

One task per bus, each strictly serial (one transaction in flight on a wire);
buses run concurrently. A device whose cycle gets no valid reply at all is backed
off exponentially (capped, with jitter so devices that died together do not come
back in lockstep) and from then on each attempt starts as a cheap probe: one block,
no immediate retries. That is what keeps one dead device from starving the live
ones: it costs one timeout per backoff period instead of every scan.

A cycle reads the device's blocks starting where the last one failed, so a device
that fails part-way still gets every block read in turn. A timeout ends the cycle
early when the device has not answered yet in it (it is most likely gone); a CRC
error or an exception reply does not (the device is there, the next block may work).

When several devices are due, the one that used the bus least lately goes first,
use counted in its own nominal cycles: healthy devices take turns, and one that
answers but slowly or garbled (so it is not backed off) gets turns in proportion
to what it costs instead of setting everyone's pace. A port that goes away pauses
its bus briefly without blaming any device; the bus reopens it.

Statistics per device (requests, ok, timeouts, garbled, exceptions by code, latency
percentiles, last good values, state) live in ``pollstats``; rendering elsewhere.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

from rtupoll.config.site import BusConfig, DeviceConfig, Site
from rtupoll.errors import DeviceException, DeviceTimeout, FrameError, PortError, RtupollError
from rtupoll.jobs.device import probe_variant, read_block
from rtupoll.jobs.stats import BusLoad, DeviceStats, Reading, State
from rtupoll.model.planner import Block, plan
from rtupoll.model.profile import Field
from rtupoll.rtu import Framing, Table, read_frame_sizes, transaction_wire_time

T = TypeVar("T")
Clock = Callable[[], float]
PORT_RETRY_CAP = 10.0  # seconds between attempts to reopen a port that went away
USAGE_MEMORY = 30.0  # seconds over which bus use counts when sharing the bus
Sink = Callable[["DevicePoller", list[Reading]], None]


class Transport(Protocol):
    """What the scheduler needs of a bus (``rtupoll.io.bus.Bus`` is one)."""

    async def open(self) -> None: ...
    async def close(self) -> None: ...
    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0) -> tuple[int, ...]: ...


@dataclass(frozen=True)
class Backoff:
    """Delay before the next attempt after ``failures`` failed cycles in a row.

    ``max(base, interval) * factor ** (failures - 1)``, capped, times a random
    factor in ``1 ± jitter``. After ``offline_after`` failed cycles a device is
    shown offline (it is still probed at the backed-off rate).
    """

    base: float = 1.0
    factor: float = 2.0
    cap: float = 60.0
    jitter: float = 0.2
    offline_after: int = 3

    def delay(self, failures: int, interval: float, rand: Callable[[], float]) -> float:
        raw = min(self.cap, max(self.base, interval) * self.factor ** max(0, failures - 1))
        return raw * (1 + self.jitter * (2 * rand() - 1))


class DevicePoller:
    """One device's plan and state; ``cycle`` reads it once through a transport."""

    def __init__(self, config: DeviceConfig, bus: BusLoad, *, framing: Framing | None = None,
                 clock: Clock = time.monotonic, wall: Clock = time.time) -> None:
        self.config = config
        self.blocks: tuple[Block, ...] = plan(config.fields, config.profile)
        # fields only some generations of the map have (IRNET data structure 1): ask the
        # device which it is before reading them, and report the others as absent
        self.variant_unknown = config.profile.variant is not None and any(
            f.since for f in config.fields)
        self.absent: tuple[Field, ...] = ()
        self.absent_why = ""
        self.stats = DeviceStats()
        self.load = bus
        self.next_due = 0.0
        self.resume = 0  # index of the block the next cycle starts at
        self.last_run = -1  # sequence number of the last cycle, for round-robin ties
        self._clock, self._wall = clock, wall
        self.framing = framing or Framing(9600)
        self.nominal = nominal_cycle(self.blocks, config, self.framing)
        self._used, self._used_at = 0.0, clock()  # in nominal cycles, decaying

    def used(self, now: float) -> float:
        """Bus time this device took lately, in its own nominal cycles (see ``next_device``),
        decayed over ``USAGE_MEMORY`` seconds."""
        return self._used * math.exp((self._used_at - now) / USAGE_MEMORY)

    def charge(self, now: float, seconds: float) -> None:
        self._used, self._used_at = self.used(now) + seconds / self.nominal, now

    async def cycle(self, transport: Transport) -> list[Reading]:
        """Read every block once (from ``resume``); one reading per field, in field order.

        After a failed cycle the first block is a probe (no immediate retries): a
        device that is gone then costs one timeout, not ``1 + retries`` of them.
        """
        cfg, st = self.config, self.stats
        probing = st.failures > 0
        answered, timeouts = False, 0
        stopped: str | None = None
        first_failed: int | None = None
        out: dict[str, Reading] = {}
        if self.variant_unknown:
            silent = await self._probe_variant(transport, 0 if probing else cfg.retry_count)
            if silent:  # gone: one timeout, as for a first block that gets no reply
                wall = self._wall()
                readings = [Reading(wall, cfg, f, None, "timeout", silent) for f in cfg.fields]
                st.record(readings, answered=False)
                return readings
            answered = not self.variant_unknown  # the probe had its answer
        n = len(self.blocks)
        answered = answered or n == 0  # every field asked for is absent: nothing can fail
        for k in range(n):
            idx = (self.resume + k) % n
            block = self.blocks[idx]
            if stopped is not None:
                for f in block.fields:
                    out[f.name] = Reading(self._wall(), cfg, f, None, "skipped", stopped)
                continue
            retries = 0 if probing and not answered else cfg.retry_count
            status, error, values = await self._transact(read_block(
                transport, cfg.address, block, timeout=cfg.response_timeout, retries=retries))
            if status == "ok":
                answered = True
                wall = self._wall()
                for fv in values or ():
                    out[fv.field.name] = Reading(wall, cfg, fv.field, fv, "ok")
                continue
            if status == "exception":
                answered = True
            elif status == "timeout":
                timeouts += 1
                if not answered or timeouts > 1:
                    stopped = f"not read: {cfg.spec} stopped answering"
            if first_failed is None:
                first_failed = idx
            wall = self._wall()
            for f in block.fields:
                out[f.name] = Reading(wall, cfg, f, None, status, error)
        self.resume = 0 if first_failed is None else first_failed
        for f in self.absent:
            out[f.name] = Reading(self._wall(), cfg, f, None, "absent", self.absent_why)
        readings = [out[f.name] for f in cfg.fields if f.name in out]
        st.record(readings, answered)
        return readings

    async def _probe_variant(self, transport: Transport, retries: int) -> str:
        """Learn the device's variant once (until it answers, plan for the newest map);
        returns the error when the device did not answer at all."""
        cfg = self.config
        status, error, variant = await self._transact(probe_variant(
            transport, cfg.profile, cfg.address, timeout=cfg.response_timeout, retries=retries))
        if status != "ok":
            return error if status == "timeout" else ""  # else: the reads say what is wrong
        self.variant_unknown = False
        if variant is None:
            return ""
        self.blocks = plan(cfg.fields, cfg.profile, variant=variant)
        self.nominal = nominal_cycle(self.blocks, cfg, self.framing)
        self.absent = tuple(f for f in cfg.fields if f.since > variant)
        assert cfg.profile.variant is not None
        self.absent_why = f"not in {cfg.profile.variant.name} {variant}"
        self.resume = 0
        return ""

    async def _transact(self, read: Awaitable[T]) -> tuple[str, str, T | None]:
        """One read (not yet awaited), timed and counted: (status, error, what it read)."""
        cfg, st = self.config, self.stats
        start = self._clock()
        status, error, values = "ok", "", None
        try:
            values = await read
        except DeviceTimeout as exc:
            status, error = "timeout", str(exc) or f"no response from {cfg.spec}"
            st.timeouts += 1
        except FrameError as exc:
            status, error = "garbled", str(exc)
            st.garbled += 1
        except DeviceException as exc:
            status, error = "exception", str(exc)
            st.exceptions[exc.code] += 1
        now = self._clock()
        st.requests += 1
        culprit = self.load.add(now, now - start,
                                failed_by=self if status in ("timeout", "garbled") else None)
        # the bus's quiet period after a failure is the failing device's cost, not ours
        (culprit if isinstance(culprit, DevicePoller) else self).charge(now, now - start)
        if status == "ok":
            st.ok += 1
            if culprit is None:
                st.latencies.append(now - start)
        return status, error, values

    def schedule(self, started: float, backoff: Backoff, rand: Callable[[], float]) -> None:
        """Set ``next_due`` after a cycle that started at ``started``."""
        st = self.stats
        if st.failures == 0:
            self.next_due = started + self.config.interval
            st.state = State.ONLINE
        else:
            self.next_due = self._clock() + backoff.delay(st.failures, self.config.interval,
                                                           rand)
            st.state = State.OFFLINE if st.failures >= backoff.offline_after else State.RETRYING


class BusPoller:
    """One bus: its transport and its devices, polled one transaction at a time."""

    def __init__(self, config: BusConfig, transport: Transport, *, backoff: Backoff,
                 clock: Clock = time.monotonic, wall: Clock = time.time,
                 rand: Callable[[], float] = random.random) -> None:
        self.config, self.transport, self.backoff = config, transport, backoff
        self.load = BusLoad(clock())
        self.devices = [DevicePoller(d, self.load, framing=config.framing, clock=clock,
                                     wall=wall)
                        for d in config.devices]
        self._clock, self._wall, self._rand = clock, wall, rand
        self._seq = 0
        self._port_failures = 0
        self.port_error = ""  # the last port failure, while the port is gone

    def next_device(self) -> DevicePoller:
        """Among the devices due, the one that used the bus least lately (ties: the one that
        waited longest); when none is due, the one due soonest.

        Use is counted in each device's *nominal* cycles (its plan's wire time plus its
        turnaround), so healthy devices simply take turns, while one whose cycles cost
        far more than they should (late answers, garbled replies and their timeouts,
        yet answering, so not backed off) gets turns in proportion: it cannot drag the
        live ones down to its pace when the bus is saturated.
        """
        now = self._clock()
        due = [d for d in self.devices if d.next_due <= now]
        if due:
            return min(due, key=lambda d: (d.used(now), d.last_run))
        return min(self.devices, key=lambda d: (d.next_due, d.last_run))

    async def run_one(self, dev: DevicePoller, sink: Sink) -> None:
        started = self._clock()
        self._seq += 1
        dev.last_run = self._seq
        try:
            readings = await dev.cycle(self.transport)
        except PortError as exc:
            # the adapter vanished (or the gateway went away): no device is to blame, so
            # none is backed off; the whole bus pauses briefly and the bus reopens the port
            self.port_error = str(exc)
            self._port_failures += 1
            readings = [Reading(self._wall(), dev.config, f, None, "port", str(exc))
                        for f in dev.config.fields]
            dev.stats.latest.update({r.field.name: r for r in readings})
            pause = min(PORT_RETRY_CAP, 0.5 * 2 ** min(self._port_failures, 10))
            for d in self.devices:
                d.next_due = max(d.next_due, self._clock() + pause)
        else:
            self.port_error, self._port_failures = "", 0
            dev.schedule(started, self.backoff, self._rand)
        sink(dev, readings)

    async def run(self, sink: Sink, stop: asyncio.Event) -> None:
        while not stop.is_set():
            dev = self.next_device()
            wait = dev.next_due - self._clock()
            if wait > 0:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(stop.wait(), wait)
                continue
            await self.run_one(dev, sink)
            await asyncio.sleep(0)  # let the other buses and the display run

    async def scan_once(self, sink: Sink) -> None:
        for dev in self.devices:
            await self.run_one(dev, sink)


def nominal_cycle(blocks: Sequence[Block], config: DeviceConfig, framing: Framing) -> float:
    """What one healthy cycle should cost: each read's frames and silences on the wire
    (``rtu.transaction_wire_time``) plus the device's turnaround."""
    total = 0.0
    for b in blocks:
        request, response = read_frame_sizes(b.count, coils=not b.table.is_register)
        total += transaction_wire_time(framing, request, response)
        total += config.profile.limits.turnaround
    return max(total, 1e-3)


OpenBus = Callable[[BusConfig], Transport]


def open_real_bus(config: BusConfig) -> Transport:
    """A ``rtupoll.io.bus.Bus`` for the configured port (imported here: pymodbus is slow)."""
    from rtupoll.io.bus import Bus, PortSettings

    return Bus(PortSettings(port=config.port, baudrate=config.baudrate, parity=config.parity,
                            bytesize=config.bytesize, stopbits=config.stopbits,
                            deassert_dtr=config.deassert_dtr))


class Scheduler:
    """Every bus of a site, polled concurrently; readings go to ``sink`` per device cycle."""

    def __init__(self, site: Site, *, open_bus: OpenBus = open_real_bus,
                 backoff: Backoff | None = None, clock: Clock = time.monotonic,
                 rand: Callable[[], float] = random.random) -> None:
        self.site = site
        self.backoff = backoff or Backoff()
        self.started = clock()
        self.buses = [BusPoller(b, open_bus(b), backoff=self.backoff, clock=clock, rand=rand)
                      for b in site.buses]
        self.clock = clock
        self._opened: list[BusPoller] = []

    async def open(self) -> None:
        """Open every port, or none: a port that cannot be opened is a configuration error."""
        try:
            for bp in self.buses:
                await bp.transport.open()
                self._opened.append(bp)
        except RtupollError:
            await self.close()
            raise

    async def close(self) -> None:
        for bp in reversed(self._opened):
            with contextlib.suppress(Exception):
                await bp.transport.close()
        self._opened.clear()

    async def run(self, sink: Sink, stop: asyncio.Event) -> None:
        """Poll until ``stop`` is set; a cycle in flight then is abandoned, not half-reported."""
        tasks = [asyncio.create_task(bp.run(sink, stop)) for bp in self.buses]
        stopper = asyncio.create_task(stop.wait())
        try:
            done, _ = await asyncio.wait([*tasks, stopper], return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not stopper:
                    t.result()  # a bug in a bus task: surface it rather than poll half a site
        finally:
            for t in [*tasks, stopper]:
                t.cancel()
            await asyncio.gather(*tasks, stopper, return_exceptions=True)

    async def scan_once(self, sink: Sink) -> None:
        """Every device once (buses concurrently), for ``poll --once``."""
        await asyncio.gather(*(bp.scan_once(sink) for bp in self.buses))

    def pollers(self) -> Sequence[DevicePoller]:
        return [d for bp in self.buses for d in bp.devices]
