"""The scheduler's decisions, in virtual time: backoff, probing, resuming, fairness.

A scripted bus (tests/virtual.py) stands in for the line and advances the virtual clock
by what each transaction would cost, so these tests show *what* the scheduler does
(which block, which retries, which device next) without waiting. ``test_poll*.py`` drive the real
bus and simulator end to end.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

import pytest
from virtual import START, ScriptedBus, VirtualClock, polled, run_virtual

from rtupoll.config.site import BusConfig, DeviceConfig, from_specs
from rtupoll.jobs.scheduler import Backoff, BusPoller, DevicePoller
from rtupoll.jobs.stats import BusLoad, Reading, State
from rtupoll.percentiles import quantile


def radar(address: int = 2, interval: float = 1.0) -> DeviceConfig:
    """The radar sensor: five fields, each read alone, so five blocks a cycle."""
    return from_specs("/dev/null", [("radar-level", address)], interval=interval).buses[0] \
        .devices[0]


def poller(dev: DeviceConfig, clock: VirtualClock) -> DevicePoller:
    return DevicePoller(dev, BusLoad(clock()), clock=clock, wall=clock)


def addresses(bus: ScriptedBus) -> list[int]:
    return [a for _, a, _ in bus.calls]


def run(coro: object) -> list[Reading]:
    return asyncio.run(coro)  # type: ignore[arg-type]


def test_backoff_doubles_from_the_interval_up_to_the_cap_within_the_jitter() -> None:
    b = Backoff(base=1.0, factor=2.0, cap=60.0, jitter=0.2)
    middle = [b.delay(n, 0.5, lambda: 0.5) for n in range(1, 9)]
    assert middle == [1, 2, 4, 8, 16, 32, 60, 60]
    assert b.delay(1, 5.0, lambda: 0.5) == 5.0  # never sooner than the device's own interval
    assert b.delay(3, 1.0, lambda: 0.0) == pytest.approx(4 * 0.8)
    assert b.delay(3, 1.0, lambda: 1.0) == pytest.approx(4 * 1.2)


def test_a_device_offline_for_days_stays_at_the_cap() -> None:
    """Thousands of failed cycles in a row (a day at the 60 s cap is 1440): still the cap,
    never an overflow that would stop the scheduler."""
    b = Backoff(base=1.0, factor=2.0, cap=60.0, jitter=0.2)
    assert [b.delay(n, 1.0, lambda: 0.5) for n in (1025, 5000, 10**6)] == [60, 60, 60]


def test_a_healthy_cycle_reads_every_block_once_with_the_profiles_retries() -> None:
    clock = VirtualClock(START)
    bus, dev = ScriptedBus(clock), poller(radar(), clock)
    readings = run(dev.cycle(bus))
    assert addresses(bus) == [0, 1, 2, 3, 0x10]
    assert {r for _, _, r in bus.calls} == {dev.config.retry_count}
    assert [r.status for r in readings] == ["ok"] * 5
    assert [r.field.name for r in readings] == [f.name for f in dev.config.fields]
    assert dev.stats.ok == dev.stats.requests == 5 and dev.stats.failures == 0


def test_after_a_timeout_the_next_cycle_resumes_at_the_block_that_failed() -> None:
    clock = VirtualClock(START)
    bus, dev = ScriptedBus(clock, {2: lambda a, n: "timeout" if n == 3 else "ok"}), \
        poller(radar(), clock)
    first = run(dev.cycle(bus))
    # the device had answered in this cycle, so one timeout does not end it
    assert [r.status for r in first] == ["ok", "ok", "timeout", "ok", "ok"]
    assert first[2].value is None and "no response" in first[2].error
    bus.calls.clear()
    run(dev.cycle(bus))
    assert addresses(bus) == [2, 3, 0x10, 0, 1]


def test_a_device_that_stops_answering_is_probed_cheaply_and_backed_off() -> None:
    clock = VirtualClock(START)
    bus = ScriptedBus(clock, {2: lambda a, n: "timeout"})
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=(radar(),)), bus,
                   backoff=Backoff(), clock=clock, wall=clock, rand=lambda: 0.5)
    dev = bp.devices[0]
    sink: list[list[Reading]] = []
    states, gaps = [], []
    for _ in range(6):
        clock.now = max(clock.now, dev.next_due)
        before = clock.now
        asyncio.run(bp.run_one(dev, lambda d, rs: sink.append(rs)))
        states.append(dev.stats.state)
        gaps.append(round(dev.next_due - before, 2))
    # one block per attempt: the first with the profile's retries, then probes without
    assert [r for _, _, r in bus.calls] == [1, 0, 0, 0, 0, 0]
    assert addresses(bus) == [0] * 6
    assert states == [State.RETRYING, State.RETRYING, State.OFFLINE, State.OFFLINE,
                      State.OFFLINE, State.OFFLINE]
    assert gaps == [0.6 + 1.0, 0.3 + 2.0, 0.3 + 4.0, 0.3 + 8.0, 0.3 + 16.0, 0.3 + 32.0]
    # every field is reported, none with a value: the block tried timed out, the rest skipped
    assert [r.status for r in sink[-1]] == ["timeout", "skipped", "skipped", "skipped",
                                            "skipped"]
    assert all(r.value is None for rs in sink for r in rs)


def test_a_dead_device_with_variant_fields_costs_one_probe_per_attempt_too() -> None:
    """Fields only some variants have make the first read a variant probe (IRNET input
    0x0400); for a dead device that probe is the whole attempt, without retries."""
    clock = VirtualClock(START)
    bus = ScriptedBus(clock, {1: lambda a, n: "timeout"})
    irnet = from_specs("/dev/null", [("net-irnet-pro", 1)],
                       fields=["concentration", "uart_speed"]).buses[0].devices[0]
    bp = BusPoller(BusConfig("b", "/dev/null", 4800, devices=(irnet,)), bus,
                   backoff=Backoff(), clock=clock, wall=clock, rand=lambda: 0.5)
    dev = bp.devices[0]
    sink: list[list[Reading]] = []
    for _ in range(4):
        clock.now = max(clock.now, dev.next_due)
        asyncio.run(bp.run_one(dev, lambda d, rs: sink.append(rs)))
    assert bus.calls == [(1, 0x0400, 1), (1, 0x0400, 0), (1, 0x0400, 0), (1, 0x0400, 0)]
    assert [r.status for r in sink[-1]] == ["timeout", "timeout"]
    assert dev.stats.timeouts == 4 and dev.stats.state is State.OFFLINE


def test_a_device_that_comes_back_is_online_again_at_its_own_rate() -> None:
    clock = VirtualClock(START)
    dead = {"yes": True}
    bus = ScriptedBus(clock, {2: lambda a, n: "timeout" if dead["yes"] else "ok"})
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=(radar(),)), bus,
                   backoff=Backoff(), clock=clock, wall=clock, rand=lambda: 0.5)
    dev = bp.devices[0]
    for _ in range(4):
        clock.now = max(clock.now, dev.next_due)
        asyncio.run(bp.run_one(dev, lambda d, rs: None))
    assert dev.stats.state is State.OFFLINE
    dead["yes"] = False
    bus.calls.clear()
    clock.now = dev.next_due
    start = clock.now
    asyncio.run(bp.run_one(dev, lambda d, rs: None))
    # the probe (no retries) answered, so the rest of the cycle ran with normal retries
    assert bus.calls == [(2, 0, 0), (2, 1, 1), (2, 2, 1), (2, 3, 1), (2, 0x10, 1)]
    assert dev.stats.state is State.ONLINE and dev.stats.failures == 0
    assert dev.next_due == start + dev.config.interval


def test_an_exception_reply_is_counted_by_code_and_the_rest_of_the_device_is_read() -> None:
    clock = VirtualClock(START)
    bus = ScriptedBus(clock, {2: lambda a, n: "exc02" if a == 1 else "ok"})
    dev = poller(radar(), clock)
    readings = run(dev.cycle(bus))
    assert [r.status for r in readings] == ["ok", "exception", "ok", "ok", "ok"]
    assert "exception 02 ILLEGAL DATA ADDRESS" in readings[1].error
    assert dev.stats.exceptions == {2: 1} and dev.stats.failures == 0


def test_garbled_replies_are_counted_and_do_not_end_the_cycle() -> None:
    clock = VirtualClock(START)
    bus = ScriptedBus(clock, {2: lambda a, n: "crc" if a in (0, 2) else "ok"})
    dev = poller(radar(), clock)
    readings = run(dev.cycle(bus))
    assert [r.status for r in readings] == ["garbled", "ok", "garbled", "ok", "ok"]
    assert dev.stats.garbled == 2 and dev.resume == 0


def test_a_dead_device_does_not_starve_the_live_ones() -> None:
    """Devices polled as fast as possible for 150 virtual seconds: with one of five dead,
    the other four get nearly the scans they get on a bus of their own."""

    def scans(present: Sequence[int], dead: Sequence[int] = ()) -> dict[int, int]:
        clock = VirtualClock(START)
        devs = tuple(radar(a, interval=0) for a in present)
        bus = ScriptedBus(clock, {a: (lambda a_, n: "timeout") for a in dead})
        bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=devs), bus,
                       backoff=Backoff(), clock=clock, wall=clock, rand=lambda: 0.5)
        run_virtual(polled(bp, 150), clock)  # BusPoller.run itself, in virtual time
        return {d.config.address: d.stats.cycles for d in bp.devices}

    live = (1, 2, 4, 5)
    alone, with_dead = scans(live), scans((1, 2, 3, 4, 5), dead=(3,))
    assert sum(with_dead[a] for a in live) / sum(alone.values()) > 0.97
    assert with_dead[3] <= 10  # backed off to one probe a minute (8 in these 150 s)
    # the four live devices share the bus evenly
    assert max(with_dead[a] for a in live) - min(with_dead[a] for a in live) <= 1


def test_a_sink_that_holds_the_polling_holds_the_cycles_not_the_jobs() -> None:
    """A records reader that lags (ui.pipe_writer): the sink's event holds the bus's
    polling until it is set; a job submitted meanwhile (an MQTT command) still runs, and
    ``stop`` ends a held bus."""
    clock = VirtualClock(START)
    bus = ScriptedBus(clock)
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=(radar(interval=0),)), bus,
                   backoff=Backoff(), clock=clock, wall=clock)

    async def main() -> tuple[int, int, str, int, int]:
        room = asyncio.Event()
        cycles = [0]

        def sink(dev: DevicePoller, readings: list[Reading]) -> asyncio.Event | None:
            cycles[0] += 1
            if cycles[0] < 3:
                return None
            room.clear()  # (as a writer does while its reader lags)
            return room

        stop = asyncio.Event()
        task = asyncio.create_task(bp.run(sink, stop))
        await asyncio.sleep(60)
        held, calls = cycles[0], len(bus.calls)

        async def job(transport: object) -> str:
            return "ran"

        ran = await bp.submit(job)  # type: ignore[arg-type]
        await asyncio.sleep(60)
        after_job = cycles[0]
        room.set()
        await asyncio.sleep(1)
        resumed = cycles[0]
        stop.set()
        await asyncio.wait_for(task, 10)  # a held bus ends too
        return held, calls, ran, after_job, resumed

    held, calls, ran, after_job, resumed = run_virtual(main(), clock)
    assert held == 3 and calls == 15  # three cycles of five blocks, then nothing
    assert ran == "ran" and after_job == 3
    assert resumed == 4  # the reader caught up: the next cycle, held again


def test_a_slow_device_that_still_answers_gets_a_fair_share_of_time_not_of_turns() -> None:
    clock = VirtualClock(START)
    devs = tuple(radar(a, interval=0) for a in (1, 2, 3))
    bus = ScriptedBus(clock, {2: lambda a, n: "slow"})
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=devs), bus,
                   backoff=Backoff(), clock=clock, wall=clock)
    run_virtual(polled(bp, 120), clock)
    cycles = {d.config.address: d.stats.cycles for d in bp.devices}
    assert cycles[2] > 0 and bp.devices[1].stats.state is State.ONLINE
    assert abs(cycles[1] - cycles[3]) <= 1  # the healthy ones take turns
    # a healthy cycle takes 0.1 s, the slow one 4 s: each device had about a third of the time
    seconds = {1: cycles[1] * 0.1, 2: cycles[2] * 4.0, 3: cycles[3] * 0.1}
    assert max(seconds.values()) < 1.5 * min(seconds.values()), seconds


def test_due_devices_take_turns_and_slow_ones_wait_for_their_interval() -> None:
    clock = VirtualClock(START)
    devs = (radar(1, interval=0), radar(2, interval=0), radar(3, interval=10))
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=devs), ScriptedBus(clock),
                   backoff=Backoff(), clock=clock, wall=clock)
    order = []
    for _ in range(7):
        dev = bp.next_device()
        clock.now = max(clock.now, dev.next_due)
        asyncio.run(bp.run_one(dev, lambda d, rs: None))
        order.append(dev.config.address)
    assert order == [1, 2, 3, 1, 2, 1, 2]


def test_latency_percentiles_and_bus_utilisation() -> None:
    assert quantile([], 50) is None
    assert quantile([0.01 * i for i in range(1, 101)], 50) == pytest.approx(0.50)
    assert quantile([0.01 * i for i in range(1, 101)], 95) == pytest.approx(0.95)
    load = BusLoad(started=0.0)
    for i in range(10):
        load.add(end=i + 1.0, duration=0.25)
    assert load.utilisation(10.0) == pytest.approx(0.25)
    assert load.rate(10.0) == pytest.approx(1.0)
