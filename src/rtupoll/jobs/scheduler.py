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
percentiles, last good values, state) live in ``jobs.stats``; rendering elsewhere.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import time
from collections.abc import Awaitable, Callable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass, replace
from typing import Any, TypeVar

from rtupoll.backoff import after_failures
from rtupoll.config.site import BusConfig, DeviceConfig, Site
from rtupoll.errors import (
    BusError,
    DeviceException,
    DeviceTimeout,
    FrameError,
    PortError,
    RtupollError,
)
from rtupoll.io.interface import BusLike
from rtupoll.jobs.cycle import CyclePolicy
from rtupoll.jobs.device import (
    BlockRead,
    BlockValues,
    Read,
    Variant,
    after_refusal,
    needs_variant,
    probe_variant,
    read_block,
    read_fields,
)
from rtupoll.jobs.holes import HoleMemory, Register, refused_reading
from rtupoll.jobs.race import first_of
from rtupoll.jobs.stats import BusLoad, DeviceStats, Reading, State, Status
from rtupoll.jobs.timeouts import DeviceTiming
from rtupoll.model.interpret import FieldValue
from rtupoll.model.planner import Block, decode_block, plan
from rtupoll.model.profile import Field
from rtupoll.model.scaling import scale
from rtupoll.numbers import count
from rtupoll.rtu import ExceptionCode, Framing, Table, read_frame_sizes, transaction_wire_time
from rtupoll.rtu.transaction import Evidence

T = TypeVar("T")
Job = Callable[["BusLike"], Awaitable[T]]  # BusPoller.submit: work on the bus, between cycles
Clock = Callable[[], float]
# seconds a bus pauses after its port went away, doubling while it stays away
PORT_RETRY_FIRST, PORT_RETRY_CAP = 1.0, 10.0
USAGE_MEMORY = 30.0  # seconds over which bus use counts when sharing the bus
# a device cycle's readings; an event it returns holds the bus's polling until it is set
# (a records reader that lags: ui.pipe_writer), jobs and the gateway using the line meanwhile
Sink = Callable[["DevicePoller", list[Reading]], asyncio.Event | None]


@dataclass(frozen=True)
class Backoff:
    """Delay before the next attempt after ``failures`` failed cycles in a row.

    ``max(base, interval) * factor ** (failures - 1)``, capped, times a random
    factor in ``1 ± jitter`` (the one rule, ``rtupoll.backoff``). After
    ``offline_after`` failed cycles a device is shown offline (it is still probed at
    the backed-off rate).
    """

    base: float = 1.0
    factor: float = 2.0
    cap: float = 60.0
    jitter: float = 0.2
    offline_after: int = 3

    def delay(self, failures: int, interval: float, rand: Callable[[], float]) -> float:
        return after_failures(failures, first=max(self.base, interval), cap=self.cap,
                              factor=self.factor, jitter=self.jitter, rand=rand)


class DevicePoller:
    """One device's plan and state; ``cycle`` reads it once through a transport."""

    def __init__(self, config: DeviceConfig, bus: BusLoad, *, framing: Framing | None = None,
                 clock: Clock = time.monotonic, wall: Clock = time.time) -> None:
        self.config = config
        self.blocks: tuple[Block, ...] = plan(config.fields, config.profile, by_interval=True)
        # blocks whose fields have their own (slower) interval: when each was last read
        self.block_read: dict[tuple[Table, int, int], float] = {}
        # fields only some generations of the map have (IRNET data structure 1): ask the
        # device which it is before reading them, and report the others as absent
        self.variant_unknown = needs_variant(config.profile, config.fields)
        self.absent: tuple[Field, ...] = ()
        self.absent_why = ""
        self.variant: int | None = None  # as the device said (probe_variant)
        self.holes = HoleMemory()  # registers learned never to bridge (jobs.holes)
        self.refused: int | None = None  # the last transaction's exception code
        self.stats = DeviceStats()
        self.load = bus
        self.next_due = 0.0
        self.resume = 0  # index of the block the next cycle starts at
        self.last_run = -1  # sequence number of the last cycle, for round-robin ties
        self._clock, self._wall = clock, wall
        self.framing = framing or Framing(9600)
        # the timeout each transaction gets: learned from reply times (jobs.timeouts)
        self.timing = DeviceTiming(config.profile.limits.timeout, silence=self.framing.silence,
                                   ceiling=config.timeout_ceiling, pinned=config.timeout)
        self.nominal = nominal_cycle(self.blocks, config, self.framing)
        self._used, self._used_at = 0.0, clock()  # in nominal cycles, decaying
        self._scaling_of: tuple[Field, ...] | None = None  # (``_scaling``)
        self._scales = False
        # each block's last words and what they decoded to (``_decode``), by the block's id
        self._decoded: dict[int, tuple[Block, Sequence[int], list[FieldValue]]] = {}

    def used(self, now: float) -> float:
        """Bus time this device took lately, in its own nominal cycles (see ``next_device``),
        decayed over ``USAGE_MEMORY`` seconds."""
        return self._used * math.exp((self._used_at - now) / USAGE_MEMORY)

    def charge(self, now: float, seconds: float) -> None:
        self._used, self._used_at = self.used(now) + seconds / self.nominal, now

    async def cycle(self, transport: BusLike) -> list[Reading]:
        """Read every block once (from ``resume``); one reading per field, in field order.

        After a failed cycle the first block is a probe (no immediate retries): a
        device that is gone then costs one timeout, not ``1 + retries`` of them.
        """
        cfg, st = self.config, self.stats
        policy = CyclePolicy(cfg.spec, probing=st.failures > 0, retries=cfg.retry_count)
        out: dict[str, Reading] = {}
        if self.variant_unknown:
            silent = await self._probe_variant(transport, policy.retries())
            if silent:  # gone: one timeout, as for a first block that gets no reply
                wall = self._wall()
                readings = [Reading(wall, cfg, f, None, Status.TIMEOUT, silent) for f in cfg.fields]
                st.record(readings, answered=False)
                return readings
            if not self.variant_unknown:  # the probe had its answer
                policy.outcome(-1, Status.OK)
        blocks = self.blocks  # this cycle's plan (learning a hole re-plans the next one)
        n = len(blocks)
        started, attempted = self._clock(), False
        for k in range(n):
            idx = (self.resume + k) % n
            block = blocks[idx]
            if block.interval is not None and not self._due(block, started):
                continue
            attempted = True
            if policy.stopped is not None:
                for f in block.fields:
                    out[f.name] = Reading(self._wall(), cfg, f, None, Status.SKIPPED,
                                          policy.stopped)
                continue
            retries = policy.retries()
            status, error, got = await self._transact(read_block(
                transport, cfg.address, block, timeout=self.timeout(transport), retries=retries,
                patience=self.timing.patience, idle_gap=cfg.gap, decode=self._decode))
            values = got.values if got is not None else None
            if status is Status.EXCEPTION and self.refused == 2:
                found = await self._find_holes(transport, block, retries)
                if found is not None:  # the refused fields alone keep the exception
                    for f, exc in found.refused:
                        out[f.name] = Reading(self._wall(), cfg, f, None, Status.EXCEPTION,
                                              str(exc))
                    status, error, values = Status.OK, "", found.values
            policy.outcome(idx, status)
            wall = self._wall()
            if status is Status.OK:
                if block.interval is not None:
                    self.block_read[block.table, block.address, block.count] = started
                for fv in values or ():
                    out[fv.field.name] = Reading(wall, cfg, fv.field, fv, Status.OK)
                continue
            for f in block.fields:
                out[f.name] = Reading(wall, cfg, f, None, status, error)
        self.resume = policy.resume()
        if self._scaling(cfg.fields):
            scaled(out)
        for f in self.absent:
            out[f.name] = Reading(self._wall(), cfg, f, None, Status.ABSENT, self.absent_why)
        get = out.get
        readings = [r for f in cfg.fields if (r := get(f.name)) is not None]
        st.record(readings, policy.succeeded(attempted))
        return readings

    def _decode(self, block: Block, words: Sequence[int]) -> list[FieldValue]:
        """``decode_block``, once per change of a block's words: decoding is a pure function
        of the block and its words (values frozen), and most registers read the same from
        one cycle to the next."""
        last = self._decoded.get(id(block))
        if last is not None and last[0] is block and last[1] == words:
            return list(last[2])
        values = decode_block(block, words)
        self._decoded[id(block)] = (block, words, values)
        return list(values)

    def _scaling(self, fields: tuple[Field, ...]) -> bool:
        """Whether any of ``fields`` (the device's) has ``scale_by``: worked out once per
        tuple of fields, not per cycle."""
        if fields is not self._scaling_of:
            self._scaling_of, self._scales = fields, any(f.scale_by for f in fields)
        return self._scales

    def _due(self, block: Block, now: float) -> bool:
        """A block of fields with their own ``interval`` is read when that has passed, or
        at once while one of its fields has no value: its latest reading failed (a port
        that went away fails every field, the ones read just before it too)."""
        if block.interval is None:
            return True
        last = self.block_read.get((block.table, block.address, block.count))
        if last is None or now - last >= block.interval - 1e-3:
            return True
        latest = self.stats.latest
        return any((r := latest.get(f.name)) is not None and r.value is None
                   and r.status is not Status.ABSENT for f in block.fields)

    async def _probe_variant(self, transport: BusLike, retries: int) -> str:
        """Learn the device's variant once (until it answers, plan for the newest map);
        returns the error when the device did not answer at all."""
        cfg = self.config
        status, error, variant = await self._transact(probe_variant(
            transport, cfg.profile, cfg.address, timeout=self.timeout(transport),
            retries=retries, patience=self.timing.patience, idle_gap=cfg.gap))
        if status is not Status.OK or variant is None:  # no answer: the reads say what is wrong
            return error if status is Status.TIMEOUT else ""
        self._take_variant(variant.number)
        return ""

    def _take_variant(self, variant: int | None) -> None:
        """The device said which variant it is: plan for it, its missing fields absent."""
        cfg = self.config
        self.variant_unknown = False
        if variant is None:
            return
        self.variant = variant
        self.replan()
        self.absent = tuple(f for f in cfg.fields if f.since > variant)
        assert cfg.profile.variant is not None
        self.absent_why = f"not in {cfg.profile.variant.name} {variant}"

    def replan(self) -> None:
        """Plan the reads again (the variant became known, holes were learned)."""
        cfg = self.config
        self.blocks = plan(cfg.fields, cfg.profile, variant=self.variant, by_interval=True,
                           holes=self.holes.registers)
        self._decoded.clear()  # (the old blocks')
        self.nominal = nominal_cycle(self.blocks, cfg, self.framing)
        self.resume = 0

    def learn_holes(self, registers: frozenset[Register], why: str) -> bool:
        """Never bridge ``registers`` again for this device; True when any was new."""
        if not self.holes.learn(registers, why):
            return False
        self.stats.holes = list(self.holes.notes)
        self.replan()
        return True

    async def _find_holes(self, transport: BusLike, block: Block, retries: int
                          ) -> BlockRead | None:
        """``block`` got exception 02: bisect (``jobs.device.after_refusal``); what read,
        and which fields the device refuses; from then on the refused registers are not
        bridged and a refused field is read alone."""
        key = (block.table, block.address, block.count)
        if key in self.holes.tried:
            return None
        refusal = DeviceException(ExceptionCode.ILLEGAL_ADDRESS, unit=self.config.address,
                                  function=block.table.read_function)
        try:
            found = await after_refusal(transport, self.config.address, block, refusal,
                                        timeout=self.timeout(transport), retries=retries)
        except BusError:
            return None
        if found is None:
            self.holes.tried.add(key)
            return None
        self.learn_holes(found.holes, refused_reading(block))
        return found

    async def read_now(self, transport: BusLike, fields: Sequence[Field]) -> Read:
        """``fields`` read now, between cycles (MQTT ``get``), by the one read job with
        what the cycles learned: the variant (asked first while unknown) and the holes. What
        this read finds (the variant it asked, holes) is learned as the cycle's is: the cycles
        plan for it."""
        cfg = self.config
        got = await read_fields(transport, cfg.profile, cfg.address, fields,
                                timeout=cfg.response_timeout, retries=cfg.retry_count,
                                variant=self.variant, probe=self.variant is None,
                                holes=self.holes.registers)
        if self.variant is None and got.variant is not None:
            self._take_variant(got.variant)
        for block, registers in got.holes:
            self.learn_holes(registers, refused_reading(block))
        return got

    def timeout(self, transport: BusLike) -> float:
        """The next transaction's timeout: pinned, or learned (``jobs.timeouts``)."""
        cfg = self.config
        return self.timing.before(transport, cfg.address, pinned=cfg.timeout,
                                  ceiling=cfg.timeout_ceiling)

    async def _transact(self, read: Awaitable[T]) -> tuple[Status, str, T | None]:
        """One read (not yet awaited), timed and counted: (status, error, what it read).
        The timing learns from its evidence: the ``BlockValues``'s or ``Variant``'s, or
        its bus error's."""
        cfg, st = self.config, self.stats
        start = self._clock()
        status, error, values = Status.OK, "", None
        evidence: Evidence | None = None
        self.refused = None
        try:
            values = await read
            if isinstance(values, (BlockValues, Variant)):
                evidence = values.evidence
        except DeviceTimeout as exc:
            status, error = Status.TIMEOUT, str(exc) or f"no response from {cfg.spec}"
            st.timeouts += 1
            evidence = exc.evidence
        except FrameError as exc:
            status, error = Status.GARBLED, str(exc)
            st.garbled += 1
            evidence = exc.evidence
        except DeviceException as exc:
            status, error = Status.EXCEPTION, str(exc)
            st.exceptions[exc.code] += 1
            self.refused = exc.code
            evidence = exc.evidence
        now = self._clock()
        st.requests += 1
        timing = self.timing
        timing.learn(evidence)
        st.timeout, st.timeout_source = timing.timeout, timing.source
        if st.line is None:
            st.line = timing.counts
        # the bus's quiet period after a failure is the failing device's cost, not ours
        own = self.load.add(now, now - start, self,
                            failed=status is Status.TIMEOUT or status is Status.GARBLED)
        if status is Status.OK:
            st.ok += 1
            if own:
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


def scaled(out: dict[str, Reading]) -> None:
    """This cycle's readings of fields with ``scale_by``, multiplied by the factors read in
    the same cycle; a field whose factor has no value gets none either (``unscaled``)."""
    for name, r in out.items():
        if r.value is None or not r.field.scale_by:
            continue
        got = {n: out[n].value or f"{out[n].status}: {out[n].error}"
               for n in r.field.scale_by if n in out}
        res = scale(r.value, got)
        out[name] = replace(r, value=res) if isinstance(res, FieldValue) else \
            Reading(r.time, r.device, r.field, None, Status.UNSCALED, res.reason)


class BusPoller:
    """One bus: its transport and its devices, polled one transaction at a time."""

    def __init__(self, config: BusConfig, transport: BusLike, *, backoff: Backoff,
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
        # held for each device cycle: the gateway shares the line (``share_line``)
        self.turn: Callable[[], AbstractAsyncContextManager[None]] = contextlib.nullcontext
        # from outside the schedule (MQTT get/set): devices to read next, jobs to run
        # between two cycles, and the event that wakes an idle bus for them
        self._urgent: list[DevicePoller] = []
        self._jobs: list[tuple[Job[Any], asyncio.Future[Any]]] = []
        self._wake = asyncio.Event()

    def share_line(self, turn: Callable[[], AbstractAsyncContextManager[None]]) -> None:
        """Others use this line too (a gateway's clients, ``rtupoll.gateway.turns``): each
        device cycle waits for ``turn()`` and holds it while it reads."""
        self.turn = turn

    def next_device(self) -> DevicePoller:
        """Among the devices due, the one that used the bus least lately (ties: the one that
        waited longest); when none is due, the one due soonest.

        Use is counted in each device's *nominal* cycles (its plan's wire time plus its
        turnaround), so healthy devices simply take turns, while one whose cycles cost
        far more than they should (late answers, garbled replies and their timeouts,
        yet answering, so not backed off) gets turns in proportion: it cannot drag the
        live ones down to its pace when the bus is saturated.
        """
        for d in self._urgent:  # poll_now: ahead of every other device
            if d in self.devices:
                return d
        now = self._clock()
        due = [d for d in self.devices if d.next_due <= now]
        if due:
            return min(due, key=lambda d: (d.used(now), d.last_run))
        return min(self.devices, key=lambda d: (d.next_due, d.last_run))

    async def run_one(self, dev: DevicePoller, sink: Sink) -> asyncio.Event | None:
        """One cycle of ``dev``, its readings given to ``sink``; what ``sink`` returned."""
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
            readings = [Reading(self._wall(), dev.config, f, None, Status.PORT, str(exc))
                        for f in dev.config.fields]
            dev.stats.latest.update({r.field.name: r for r in readings})
            pause = after_failures(self._port_failures, first=PORT_RETRY_FIRST,
                                   cap=PORT_RETRY_CAP)
            for d in self.devices:
                d.next_due = max(d.next_due, self._clock() + pause)
        else:
            self.port_error, self._port_failures = "", 0
            dev.schedule(started, self.backoff, self._rand)
        return sink(dev, readings)

    async def run(self, sink: Sink, stop: asyncio.Event) -> None:
        held: asyncio.Event | None = None  # what the sink holds the polling on
        while not stop.is_set():
            if not self.devices:  # a bus only served to gateway clients
                await stop.wait()
                return
            self._wake.clear()
            if self._jobs:
                async with self.turn():
                    await self._run_job(*self._jobs.pop(0))
                continue
            if held is not None and not held.is_set():
                await first_of(held.wait(), stop.wait(), self._wake.wait())
                continue
            dev = self.next_device()
            wait = dev.next_due - self._clock()
            if wait > 0:
                await self._idle(stop, wait)
                continue
            if dev in self._urgent:
                self._urgent.remove(dev)
            asked = dev.stats.requests
            async with self.turn():
                held = await self.run_one(dev, sink)
            if dev.stats.requests == asked:  # it waited for no reply: let the others run
                await asyncio.sleep(0)

    async def scan_once(self, sink: Sink) -> None:
        for dev in self.devices:
            held = await self.run_one(dev, sink)
            if held is not None:
                await held.wait()

    def poll_now(self, dev: DevicePoller) -> None:
        """Read ``dev`` next, ahead of the schedule (a backed-off device too), once."""
        dev.next_due = min(dev.next_due, self._clock())
        if dev not in self._urgent:
            self._urgent.append(dev)
        self._wake.set()

    def submit(self, job: Job[T]) -> asyncio.Future[T]:
        """Run ``job(transport)`` on this bus between two cycles, before any device that is
        due (writes, reads of unpolled fields); its result or error comes in the future.
        Only while ``run`` runs."""
        future: asyncio.Future[T] = asyncio.get_running_loop().create_future()
        self._jobs.append((job, future))
        self._wake.set()
        return future

    async def _run_job(self, job: Job[Any], future: asyncio.Future[Any]) -> None:
        if future.cancelled():
            return
        try:
            result = await job(self.transport)
        except Exception as exc:  # the job's own error, for its caller
            if not future.cancelled():
                future.set_exception(exc)
        else:
            if not future.cancelled():
                future.set_result(result)

    async def _idle(self, stop: asyncio.Event, wait: float) -> None:
        """Sleep up to ``wait`` s; ``stop``, ``poll_now`` or ``submit`` end it early."""
        await first_of(stop.wait(), self._wake.wait(), timeout=wait)

    def reconfigure(self, config: BusConfig) -> list[str]:
        """``Scheduler.reload`` for this bus (same port and settings): what changed."""
        old = {d.config.name: d for d in self.devices}
        devices: list[DevicePoller] = []
        changes: list[str] = []
        for dc in config.devices:
            dev = old.pop(dc.name, None)
            if dev is not None and (dev.config.profile, dev.config.address,
                                    dev.config.fields) == (dc.profile, dc.address, dc.fields):
                was = dev.config
                dev.config = dc
                if dc.interval != was.interval:
                    changes.append(f"{dc.name}: interval {was.interval:g} s -> "
                                   f"{dc.interval:g} s")
                    if dev.stats.failures == 0:  # a backed-off device keeps its backoff
                        dev.next_due = min(dev.next_due, self._clock() + dc.interval)
                if (dc.timeout, dc.retries) != (was.timeout, was.retries):
                    changes.append(f"{dc.name}: timeout/retries changed")
                devices.append(dev)
                continue
            changes.append(f"{'changed' if dev is not None else 'added'} {dc.name} "
                           f"({dc.spec}) on {config.name}")
            devices.append(DevicePoller(dc, self.load, framing=config.framing,
                                        clock=self._clock, wall=self._wall))
        changes += [f"removed {name} from {config.name}" for name in old]
        self.config, self.devices = config, devices
        return changes


def _serial(bus: BusConfig) -> tuple[object, ...]:
    """What a bus's port is opened with: equal means the open port can stay open."""
    return (bus.port, bus.baudrate, bus.parity, bus.bytesize, bus.stopbits, bus.deassert_dtr,
            bus.echo, bus.rs485, bus.idle_gap)


def nominal_cycle(blocks: Sequence[Block], config: DeviceConfig, framing: Framing) -> float:
    """What one healthy cycle should cost: each read's frames and silences on the wire
    (``rtu.transaction_wire_time``) plus the device's turnaround and idle gap."""
    total = 0.0
    for b in blocks:
        request, response = read_frame_sizes(b.count, coils=not b.table.is_register)
        total += transaction_wire_time(framing, request, response)
        total += config.profile.limits.turnaround + config.gap
    return max(total, 1e-3)


OpenBus = Callable[[BusConfig], BusLike]


def open_real_bus(config: BusConfig) -> BusLike:
    """A ``rtupoll.io.bus.Bus`` for the configured port (imported here: pymodbus is slow)."""
    from rtupoll.io.bus import Bus, PortSettings
    from rtupoll.io.port_settings import Rs485

    bus = Bus(PortSettings(port=config.port, baudrate=config.baudrate, parity=config.parity,
                           bytesize=config.bytesize, stopbits=config.stopbits,
                           deassert_dtr=config.deassert_dtr, echo=config.echo,
                           rs485=Rs485(*config.rs485) if config.rs485 else None,
                           idle_gap=config.idle_gap))
    bus.line.adopt_echo = True  # an echo found without echo: carry on with it (ECHO_FOUND)
    return bus


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
        self._open_bus, self._rand = open_bus, rand
        self._tasks: dict[BusPoller, asyncio.Task[None]] = {}  # while ``run`` runs
        self._running: tuple[Sink, asyncio.Event] | None = None
        self._group: asyncio.TaskGroup | None = None  # the buses' tasks, while ``run`` runs

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
        """Poll until ``stop`` is set; a cycle in flight then is abandoned, not half-reported.
        Buses that ``reload`` adds join, buses it removes leave, while this runs."""
        self._running = (sink, stop)
        try:
            async with asyncio.TaskGroup() as group:  # an error in one bus ends them all
                self._group = group
                for bp in self.buses:
                    self._tasks[bp] = group.create_task(bp.run(sink, stop))
                await stop.wait()
                for t in self._tasks.values():
                    t.cancel()
        except ExceptionGroup as errors:
            raise _first(errors) from None
        finally:
            self._tasks, self._running, self._group = {}, None, None

    async def scan_once(self, sink: Sink) -> None:
        """Every device once (buses concurrently), for ``poll --once``."""
        try:
            async with asyncio.TaskGroup() as group:
                for bp in self.buses:
                    group.create_task(bp.scan_once(sink))
        except ExceptionGroup as errors:
            raise _first(errors) from None

    def pollers(self) -> Sequence[DevicePoller]:
        return [d for bp in self.buses for d in bp.devices]

    async def reload(self, site: Site) -> list[str]:
        """Poll ``site`` from now on, touching only what changed; returns what changed.

        A bus is the same when its port and serial settings are: its port stays open, its
        task keeps running, and devices whose reads are unchanged (profile, address,
        fields) keep their state and statistics, taking a new interval, timeout or retry
        count at once. Other buses are closed, and new ones opened (a port that cannot
        be opened yet is retried like one that went away).
        """
        old = {bp.config.port: bp for bp in self.buses}
        keep: list[BusPoller] = []
        changes: list[str] = []
        for bc in site.buses:
            bp = old.get(bc.port)
            if bp is not None and _serial(bp.config) == _serial(bc):
                del old[bc.port]
                changes += bp.reconfigure(bc)
                keep.append(bp)
                continue
            keep.append(BusPoller(bc, self._open_bus(bc), backoff=self.backoff,
                                  clock=self.clock, rand=self._rand))
        for bp in old.values():  # gone, or its serial settings changed: close it first
            task = self._tasks.pop(bp, None)
            if task is not None:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            if bp in self._opened:
                self._opened.remove(bp)
                with contextlib.suppress(Exception):
                    await bp.transport.close()
            changes.append(f"closed bus {bp.config.name} ({bp.config.port})")
        for bp in keep:
            if bp in self._opened or bp in self._tasks:
                continue
            try:
                await bp.transport.open()
                changes.append(f"opened bus {bp.config.name} ({bp.config.port}, "
                               f"{bp.config.serial_text}): {count(len(bp.devices), 'device')}")
            except RtupollError as exc:
                changes.append(f"bus {bp.config.name}: {exc} (retrying)")
            self._opened.append(bp)
            if self._running is not None and self._group is not None:
                self._tasks[bp] = self._group.create_task(bp.run(*self._running))
        self.buses[:] = keep
        self.site = site
        return changes


def _first(errors: BaseExceptionGroup[Exception]) -> Exception:
    """The error a bus task raised (the first, should several): what ``poll`` reports,
    as it would have from one task (``BrokenPipeError``: the reader went away)."""
    first = errors.exceptions[0]
    return _first(first) if isinstance(first, BaseExceptionGroup) else first
