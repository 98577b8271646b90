"""Timeouts that tune themselves (rtupoll.jobs.timeouts), in virtual time.

The estimator's rules are checked with numbers; the whole loop -- the line measuring
reply times, the scheduler's own loop (``BusPoller.run``) asking for each timeout, a
simulated device drifting or dying -- runs on ``sim.virtual.VirtualBus`` (the
simulator's engine and the real line discipline) with a virtual clock
(``virtual.run_virtual``), so minutes of polling cost milliseconds.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import os
from collections.abc import Callable
from pathlib import Path

import pytest
from virtual import heard_nothing, polled, run_virtual, simulated

from rtupoll.config.library import load_one
from rtupoll.config.site import BusConfig, from_specs
from rtupoll.errors import DeviceTimeout
from rtupoll.io.latency import latency_timer, latency_warning
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.jobs.stats import State
from rtupoll.jobs.timeouts import (
    CEILING,
    FLOOR,
    MARGIN,
    DeviceTiming,
    TimeoutEstimator,
)
from rtupoll.percentiles import quantile
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.line import LATE_FACTOR, Answer, Line, UnitCounts
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.transaction import Evidence
from rtupoll.sim.device import SimDeviceConfig as SimConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.virtual import VirtualBus, VirtualClock

# -- the line measures reply times ---------------------------------------------------


class Quiet:
    """A bus whose line has heard nothing (``BusLike``'s counting side)."""

    adapter_latency = 0.0

    def unit_counts(self, unit: int) -> UnitCounts:
        return heard_nothing(unit)


def test_the_line_measures_reply_time_from_the_requests_end_to_the_first_byte() -> None:
    framing = Framing(9600)
    line = Line(framing)
    request = ReadRequest(1, 3, 0, 2).frame()
    line.send(request, 10.0)
    end = 10.0 + framing.wire_time(len(request))
    event = line.receive(ReadReply(1, 3, (1, 2)).frame(), end + 0.042)
    assert isinstance(event, Answer)
    assert event.reply_time == pytest.approx(0.042)
    assert line.reply_time[1] == pytest.approx(0.042)


def test_a_late_reply_records_its_reply_time() -> None:
    framing = Framing(9600)
    line = Line(framing)
    first, other = ReadRequest(1, 3, 0, 2).frame(), ReadRequest(1, 3, 8, 2).frame()
    line.send(first, 0.0)
    line.expire(0.1, 0.1)
    line.send(other, 0.3)  # a different request of the same shape: the late reply is not it
    assert line.receive(ReadReply(1, 3, (1, 2)).frame(), 0.4) is None
    assert line.counts.late[1] == 1
    assert line.late_reply_time[1] == pytest.approx(0.4 - framing.wire_time(len(first)))


def test_a_short_learned_timeout_does_not_shorten_the_late_window() -> None:
    line = Line(Framing(9600))
    first, other = ReadRequest(1, 3, 0, 2).frame(), ReadRequest(1, 3, 8, 2).frame()
    line.send(first, 0.0)
    line.expire(0.03, 0.03)  # a learned 30 ms timeout
    assert line.hazard_until(other, 0.1) == pytest.approx(12 * 0.03)
    line.send(first, 1.0)
    line.expire(1.03, 0.03, 0.5)  # the request's patience: the profile's timeout
    assert line.hazard_until(other, 1.1) == pytest.approx(1.0 + 12 * 0.5)


def test_a_read_with_a_short_learned_timeout_keeps_the_profiles_patience() -> None:
    """The patience goes with the read (no bus state set beforehand): a device whose
    timeout was learned down to a few ms, silent once, is still expected to answer late
    for as long as its profile's timeout allows, in virtual time on the virtual bus."""
    clock = VirtualClock(1000.0)
    engine = Engine([SimConfig(load_one("huiwen-aq"), 3)], tick=None)
    bus = VirtualBus(engine, Framing(9600), clock=clock, sleep=clock.sleep)
    timing = DeviceTiming(0.5, silence=Framing(9600).silence)
    for _ in range(300):
        timing.estimator.answered(0.005)
    engine.devices[0].address = 99  # silent from now on
    timeout = timing.before(bus, 3)
    assert timeout < 0.05 and timing.patience == 0.5

    async def silent() -> float:
        sent = clock.now
        with pytest.raises(DeviceTimeout) as exc:
            await bus.read(3, Table.INPUT, 30006, 1, timeout=timeout,
                           patience=timing.patience)
        assert exc.value.evidence is not None and exc.value.evidence.attempts == 1
        return sent

    sent = asyncio.run(silent())
    other = ReadRequest(3, 4, 30007, 1).frame()  # the same shape: its late reply fits
    assert bus.line.hazard_until(other, clock.now) == pytest.approx(sent + 12 * 0.5, abs=0.02)


def test_a_reply_faster_than_the_wire_counts_as_zero() -> None:
    line = Line(Framing(1200))  # a simulator or gateway answers before the request "ended"
    line.send(ReadRequest(1, 3, 0, 2).frame(), 0.0)
    event = line.receive(ReadReply(1, 3, (1, 2)).frame(), 0.001)
    assert isinstance(event, Answer) and event.reply_time == 0.0


# -- the estimator -----------------------------------------------------------------


def test_it_starts_at_the_profiles_timeout_within_floor_and_ceiling() -> None:
    assert TimeoutEstimator(0.5).timeout == 0.5
    assert TimeoutEstimator(10.0).timeout == CEILING
    assert TimeoutEstimator(0.001, floor=0.03).timeout == 0.03


def test_it_goes_up_at_once_and_down_slowly() -> None:
    est = TimeoutEstimator(0.5, floor=0.02)
    for _ in range(200):
        est.answered(0.005)
    assert est.timeout == pytest.approx(0.02, abs=1e-3)  # fast device: the floor
    est.answered(0.3)
    assert est.timeout == pytest.approx(MARGIN * 0.3)  # one slow reply: up at once
    for _ in range(10):
        est.answered(0.005)
    assert est.timeout > 0.3  # ten fast answers later it still allows for that reply
    history = []
    for _ in range(400):
        est.answered(0.005)
        history.append(est.timeout)
    assert history == sorted(history, reverse=True)  # never up while fast
    drops = [a - b for a, b in itertools.pairwise(history)]
    assert max(drops) <= 0.05 * MARGIN * 0.3 + 1e-9  # no step bigger than DOWN of the way
    assert history[-1] == pytest.approx(0.02, abs=1e-3)  # and back to the floor in the end


def test_the_slow_end_not_the_mean_sets_it() -> None:
    est = TimeoutEstimator(0.5, floor=0.01)
    for i in range(128):
        est.answered(0.1 if i % 10 == 0 else 0.01)  # one reply in ten is slow
    assert est.timeout == pytest.approx(MARGIN * 0.1, rel=0.01)
    assert quantile([1, 2, 3, 4], 50) == 2 and quantile([], 99) is None


def test_a_late_reply_is_evidence_for_a_longer_timeout_up_to_the_ceiling() -> None:
    est = TimeoutEstimator(0.05, floor=0.02, ceiling=1.0)
    est.late(0.3)
    assert est.timeout == pytest.approx(MARGIN * 0.3)
    est.late(None)  # late, time unknown: at least double
    assert est.timeout == pytest.approx(1.0)  # 1.2 capped by the ceiling
    assert est.late_replies == 2


def test_a_timeout_alone_teaches_nothing_so_a_dead_device_stays_cheap() -> None:
    timing = DeviceTiming(0.5, silence=0.004)
    for _ in range(100):
        timing.estimator.answered(0.006)
    learned = timing.timeout
    for _ in range(20):
        timing.before(Quiet(), 1)
        timing.learn(Evidence(attempts=2))  # a timeout: no reply time, nothing late
    assert timing.timeout == learned < 0.05


def test_a_pinned_timeout_is_used_as_given_and_the_floor_counts_the_adapter() -> None:
    class Adapter(Quiet):
        adapter_latency = 0.016

    timing = DeviceTiming(0.5, silence=0.004)
    assert timing.before(None, 1, pinned=0.8) == 0.8 and timing.source == "pinned"
    for _ in range(300):
        timing.estimator.answered(0.001)
    assert timing.before(Adapter(), 1) == pytest.approx(FLOOR + 0.004 + 0.016)
    assert timing.source == "learned"


# -- the adapter's latency timer --------------------------------------------------


def test_latency_timer_from_sysfs_and_the_warning(tmp_path: Path) -> None:
    dev = tmp_path / "sys/bus/usb-serial/devices/ttyUSB0"
    dev.mkdir(parents=True)
    (dev / "latency_timer").write_text("16\n")
    (tmp_path / "dev/serial/by-id").mkdir(parents=True)
    (tmp_path / "dev/ttyUSB0").write_text("")
    os.symlink(tmp_path / "dev/ttyUSB0", tmp_path / "dev/serial/by-id/usb-FTDI-if00")
    root = str(tmp_path)
    assert latency_timer("/dev/ttyUSB0", root=root) == pytest.approx(0.016)
    assert latency_timer("/dev/serial/by-id/usb-FTDI-if00", root=root) == pytest.approx(0.016)
    assert latency_timer("nodtr:///dev/ttyUSB0", root=root) == pytest.approx(0.016)
    assert latency_timer("/dev/ttyUSB1", root=root) is None  # no such adapter
    assert latency_timer("/dev/pts/3", root=root) is None
    assert latency_timer("tcp://10.0.0.5:502", root=root) is None
    warning = latency_warning("/dev/ttyUSB0", 0.016)
    assert warning is not None and "16 ms" in warning and "latency_timer" in warning
    assert 'ATTR{latency_timer}="1"' in warning  # the udev rule
    assert latency_warning("/dev/ttyUSB0", 0.001) is None
    assert latency_warning("/dev/pts/3", None) is None


# -- the whole loop, in virtual time ------------------------------------------------


TimedBus = VirtualBus  # it tells reply times as ``io.bus.Bus`` does


def setup(turnaround: float) -> tuple[VirtualClock, BusPoller, Engine]:
    clock = VirtualClock()
    profile = load_one("huiwen-aq")
    engine = Engine([SimConfig(profile, 3, turnaround=turnaround)], tick=None)
    bus = TimedBus(engine, Framing(9600), clock=clock, sleep=clock.sleep)
    config: BusConfig = from_specs("virtual", [("huiwen-aq", 3)], baudrate=9600).buses[0]
    poller = BusPoller(config, bus, backoff=Backoff(), clock=clock, wall=clock,
                       rand=lambda: 0.5)
    return clock, poller, engine


def set_turnaround(engine: Engine, seconds: float) -> None:
    d = engine.devices[0]
    d.config = dataclasses.replace(d.config, turnaround=seconds)


def test_a_device_drifting_from_5_to_300_ms_and_back_is_never_offline() -> None:
    clock, bp, engine = setup(0.005)
    dev = bp.devices[0]
    states: list[State] = []
    timeouts: list[tuple[float, float]] = []  # (reply time now, timeout used)
    now_turnaround = [0.005]

    def watch() -> None:
        states.append(dev.stats.state)
        assert dev.stats.timeout is not None
        timeouts.append((now_turnaround[0], dev.stats.timeout))

    async def scenario() -> None:
        await polled(bp, 120, lambda d, rs: watch())  # learn the fast device
        fast = dev.stats.timeout
        assert fast is not None and fast < 0.1
        steps = [0.005 * 1.15 ** k for k in range(31)]  # 5 ms .. ~330 ms, 15% a step
        for t in [*steps, *reversed(steps)]:
            now_turnaround[0] = t
            set_turnaround(engine, t)
            await polled(bp, 5, lambda d, rs: watch())
        await polled(bp, 300, lambda d, rs: watch())  # long enough to come down again

    run_virtual(scenario(), clock)
    assert State.OFFLINE not in states and State.RETRYING not in states
    assert dev.stats.timeouts == 0
    peak = max(t for _, t in timeouts)
    assert peak >= 0.3  # it followed the device up
    assert all(t >= r for r, t in timeouts)  # and never waited less than the device took
    assert timeouts[-1][1] < 0.1  # and came back down
    assert dev.stats.timeout_source == "learned"


def test_a_sudden_jump_to_300_ms_costs_at_most_two_timeouts_never_offline() -> None:
    clock, bp, engine = setup(0.005)
    dev = bp.devices[0]
    states: list[State] = []

    async def scenario() -> None:
        await polled(bp, 120)
        set_turnaround(engine, 0.3)
        await polled(bp, 60, lambda d, rs: states.append(dev.stats.state))

    run_virtual(scenario(), clock)
    assert State.OFFLINE not in states
    assert dev.stats.late >= 1 or dev.stats.timeouts >= 1  # it did notice the jump
    assert dev.stats.timeouts <= 2  # the reads in flight when it jumped, no more
    assert dev.stats.timeout is not None and dev.stats.timeout >= 0.3
    assert dev.stats.state is State.ONLINE


def test_a_dead_devices_cost_per_probe_falls_to_near_its_learned_timeout() -> None:
    clock, bp, engine = setup(0.005)
    dev = bp.devices[0]
    profile_timeout = dev.config.profile.limits.timeout

    async def scenario() -> tuple[float, float]:
        await polled(bp, 120)
        learned = dev.timing.timeout
        engine.devices[0].address = 99  # gone: nothing answers 3 any more
        costs = []
        for _ in range(6):
            start = clock.now
            await bp.run_one(dev, lambda d, rs: None)
            costs.append(clock.now - start)
        return learned, max(costs[1:])  # the first cycle still had its retry

    learned, cost = run_virtual(scenario(), clock)
    assert learned < profile_timeout / 5
    framing = Framing(9600)
    # one probe: its frames, the learned timeout and the quiet period after it
    assert cost <= framing.wire_time(8 + 15) + 2 * learned + 3 * framing.silence
    assert cost < profile_timeout / 2
    assert dev.stats.state is State.OFFLINE


def test_the_poller_sends_each_read_with_the_profiles_patience() -> None:
    """Learned down to a few ms, a device that falls silent is still expected to answer
    late for ``LATE_FACTOR`` of its profile's timeouts: the poller passes the patience
    with the read, so a different read of the same shape waits that long (``rtu.line``'s
    hazard), not a few learned timeouts."""
    clock, bp, engine = setup(0.005)
    dev = bp.devices[0]
    profile_timeout = dev.config.profile.limits.timeout

    async def scenario() -> float:
        await polled(bp, 120)
        assert dev.timing.timeout < profile_timeout / 5
        engine.devices[0].address = 99  # silent from now on
        start = clock.now
        await bp.run_one(dev, lambda d, rs: None)
        return start

    start = run_virtual(scenario(), clock)
    bus = bp.transport
    assert isinstance(bus, VirtualBus) and dev.stats.timeouts >= 1
    asked = bus.sent[-1]  # the read that timed out; another of its shape:
    other = with_crc(asked[:2] + (int.from_bytes(asked[2:4], "big") + 1).to_bytes(2, "big")
                     + asked[4:6])
    assert bus.line.hazard_until(other, clock.now) >= start + LATE_FACTOR * profile_timeout


# -- scan: an address that answered late is asked again ------------------------------


def test_scan_asks_a_late_address_again_with_a_longer_timeout() -> None:
    from collections.abc import AsyncIterator
    from contextlib import asynccontextmanager

    from rtupoll.config.library import load_library
    from rtupoll.jobs.scan import Found, Setting, presence_probes, sweep

    profiles = sorted(load_library().profiles.values(), key=lambda p: p.id)
    slow = Engine([SimConfig(load_one("huiwen-aq"), 5, turnaround=0.12),
                   SimConfig(load_one("net-irnet-pro"), 9)], tick=None)
    clock = VirtualClock()

    @asynccontextmanager
    async def open_bus(s: Setting) -> AsyncIterator[TimedBus]:
        yield TimedBus(slow, s.framing, clock=clock, sleep=clock.sleep)

    found: list[Found] = []
    asyncio.run(sweep(open_bus, [Setting(9600)], range(1, 12), profiles, margin=0.04,
                      probes=presence_probes(profiles), found=found))
    by_address = {f.address: f for f in found}
    assert sorted(by_address) == [5, 9]
    late = by_address[5]
    assert late.profile is not None and late.profile.id == "huiwen-aq"
    assert any("answered late at first" in e for e in late.evidence)
    assert not any("late" in e for e in by_address[9].evidence)  # the prompt one: asked once


# -- on the wire: a real pty, pymodbus and the simulator at 9600 baud ----------------


def test_the_bus_measures_a_devices_reply_time_on_the_wire(sim: Callable[..., SimulatedBus]
                                                           ) -> None:
    from rtupoll.io.bus import Bus, PortSettings

    line = sim("huiwen-aq@3", baudrate=9600, turnaround=0.1)
    timing = DeviceTiming(0.5, silence=Framing(9600).silence)

    async def go() -> tuple[float | None, float]:
        async with Bus(PortSettings(line.port, 9600)) as bus:
            for _ in range(5):
                timeout = timing.before(bus, 3)
                reply = await bus.read(3, Table.INPUT, 30006, 8, timeout=timeout, retries=1,
                                       patience=timing.patience)
                timing.learn(reply.evidence)
            return reply.evidence.reply_time, timing.timeout

    took, learned = asyncio.run(go())
    # the device waits the silence and its turnaround; the request's own wire time (8
    # bytes, 9 ms) is not part of it
    assert took is not None and took >= 0.1
    assert learned >= MARGIN * 0.1
    assert timing.source == "learned"


@pytest.mark.timing  # a real line and the real clock: late by 80 ms, not by a busy machine
def test_scan_on_the_wire_asks_a_late_address_again(sim: Callable[..., SimulatedBus]) -> None:
    """The rule is proven in virtual time above; here the same sweep on a real pty (a
    reply late by 80 ms against a 20 ms margin). In the parallel run a busy moment once
    delayed an identifying reply past even the longer timeout (found, not identified)."""
    from collections.abc import AsyncIterator
    from contextlib import asynccontextmanager

    from rtupoll.config.library import load_library
    from rtupoll.io.bus import Bus, PortSettings
    from rtupoll.jobs.scan import Found, Setting, presence_probes, sweep

    line = sim("huiwen-aq@5", baudrate=9600, turnaround=0.08)
    profiles = sorted(load_library().profiles.values(), key=lambda p: p.id)

    @asynccontextmanager
    async def open_bus(s: Setting) -> AsyncIterator[Bus]:
        async with Bus(PortSettings(line.port, s.baudrate, s.parity)) as bus:
            yield bus

    found: list[Found] = []
    asyncio.run(sweep(open_bus, [Setting(9600)], [4, 5, 6], profiles, margin=0.02,
                      probes=presence_probes(profiles), found=found))
    assert [(f.address, f.profile.id if f.profile else None) for f in found] == \
        [(5, "huiwen-aq")]
    assert any(e.startswith("answered late at first (in ") for e in found[0].evidence)


# -- configuration ------------------------------------------------------------------


def test_timeout_ceiling_from_the_site_file_and_the_command_line(tmp_path: Path) -> None:
    from cli_runner import rtupoll

    from rtupoll.config.site import load_site
    from rtupoll.errors import ConfigError

    site = tmp_path / "site.yaml"
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n    devices:\n"
                    "      - {profile: huiwen-aq, address: 3, timeout_ceiling: 1.5}\n")
    dev = load_site(site).buses[0].devices[0]
    assert dev.timeout_ceiling == 1.5 and dev.timeout is None
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n    devices:\n"
                    "      - {profile: huiwen-aq, address: 3, timeout_ceiling: 90}\n")
    with pytest.raises(ConfigError, match=r"outside 0\.05\.\.30 s"):
        load_site(site)
    spec = from_specs("/dev/null", [("huiwen-aq", 3)], timeout_ceiling=0.8)
    assert spec.buses[0].devices[0].timeout_ceiling == 0.8
    refused = rtupoll("poll", "-c", str(site), "--timeout-ceiling", "1")
    assert refused.returncode == 2 and "--timeout-ceiling" in refused.stderr


def test_the_ceiling_bounds_what_is_learned() -> None:
    timing = DeviceTiming(0.5, silence=0.004)
    timing.before(None, 1, ceiling=0.8)
    timing.estimator.answered(2.0)
    assert timing.timeout == 0.8


def test_the_estimators_sorted_window_gives_the_percentile_of_its_last_samples() -> None:
    """The slow end is kept sorted as samples come and go; it must stay what the
    percentile of the window says, through answers and late replies, past the window."""
    import random

    from rtupoll.jobs.timeouts import QUANTILE, WINDOW

    rnd = random.Random(11)
    est = TimeoutEstimator(0.5, floor=0.001)
    for i in range(3 * WINDOW + 7):
        if i % 17 == 5:
            est.late(rnd.choice([None, rnd.uniform(0.0, 0.4)]))
        else:
            est.answered(rnd.choice([rnd.uniform(-0.01, 0.3), 0.05]))  # ties too
        slow = quantile(est.samples, QUANTILE)
        assert slow is not None
        assert est.target() == min(est.ceiling, max(est.floor, MARGIN * slow)), i
    assert len(est.samples) == WINDOW


def test_the_timing_learns_from_each_reads_evidence_and_a_late_reply_between() -> None:
    """``learn`` takes each read's evidence (its reply time, late replies); a late reply
    the line heard between two reads (while another device's request was out) raises the
    next read's timeout, read from the line's live count (no copy per transaction)."""
    line = Line(Framing(9600))

    class Counted(Quiet):
        def unit_counts(self, unit: int) -> UnitCounts:
            return UnitCounts(line, unit)

    bus, timing = Counted(), DeviceTiming(0.5, silence=0.004)
    for _ in range(30):
        timing.before(bus, 1)
        timing.learn(Evidence(reply_time=0.01, attempts=1))
    assert timing.before(bus, 1) < 0.5  # learned from the 10 ms answers
    line.counts.late[1] += 1  # a late reply, heard while another device's request was out
    line.late_reply_time[1] = 0.3
    assert timing.before(bus, 1) == pytest.approx(MARGIN * 0.3)
    timing.learn(Evidence(reply_time=0.01, late=1, late_reply_time=0.3, attempts=1))
    assert timing.estimator.late_replies == 1  # the same late reply, not counted twice
    timing.learn(None)  # a bus that told nothing: nothing learned
    assert timing.timeout == pytest.approx(MARGIN * 0.3)


def test_the_probes_reply_time_is_learned_as_every_answered_reads_is() -> None:
    """The first cycle of a device with variants (fields ``since`` one) asks its variant
    first: that answer's
    reply time (here the slowest, 0.2 s) is learned as the reads' are, so the timing
    learns from every answered transaction (``jobs.device.Variant.evidence``)."""
    bus, clock = simulated(["net-irnet-pro@1"], ["slow=0.2@1"], baudrate=9600,
                           turnaround=0.005)
    config = from_specs("virtual", [("net-irnet-pro", 1)], baudrate=9600, check_serial=False,
                        fields=["concentration", "calibration_gas_level"]).buses[0]
    bp = BusPoller(config, bus, backoff=Backoff(), clock=clock, wall=clock,
                   rand=lambda: 0.5)
    dev = bp.devices[0]
    run_virtual(bp.run_one(dev, lambda d, rs: None), clock)
    assert dev.variant == 1  # the probe was answered (the newest map)
    samples = list(dev.timing.estimator.samples)
    assert len(samples) == bus.stats.outcomes["ok"] == dev.stats.requests
    assert 0.2 <= samples[0] < 0.25  # the probe's, first
    assert max(samples[1:]) < 0.05  # the reads after it
