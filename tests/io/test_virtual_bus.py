"""The virtual bus: the simulator's engine behind the one bus interface, in virtual time.

It obeys the same line discipline as the real bus, so the rules it is used to test
elsewhere (polling, backoff) hold on the wire too; here: values, exceptions, timeouts
that cost no wall-clock time, and a late reply that is counted, not decoded.
"""

from __future__ import annotations

import asyncio

import pytest

from rtupoll.config.site import from_specs
from rtupoll.errors import DeviceException, DeviceTimeout, FrameError
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.jobs.stats import Reading, State
from rtupoll.rtu import Table
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build
from rtupoll.sim.virtual import VirtualBus, VirtualClock


def virtual(devices: list[str], faults: tuple[str, ...] = ()) -> tuple[VirtualBus, VirtualClock]:
    config = build(devices, faults=faults, seed=1, turnaround=0.002, tick=None)
    clock = VirtualClock()
    engine = Engine(config.devices, config.faults, seed=1, tick=None)
    return VirtualBus(engine, clock=clock, sleep=clock.sleep), clock


def test_values_exceptions_and_timeouts_in_virtual_time() -> None:
    bus, clock = virtual(["radar-level@2"])
    bus.engine.device(2).pin("level_cm", 333)

    async def go() -> None:
        assert (await bus.read(2, Table.HOLDING, 2, 1, timeout=0.1)).values == (333,)
        with pytest.raises(DeviceException) as exc:
            await bus.read(2, Table.INPUT, 0x4000, 1, timeout=0.1)
        assert exc.value.code in (1, 2)
        started = clock.now
        with pytest.raises(DeviceTimeout):
            await bus.read(9, Table.HOLDING, 0, 1, timeout=0.5, retries=2)
        assert clock.now - started == pytest.approx(1.5, abs=0.05)  # three attempts

    asyncio.run(go())


def test_a_late_reply_is_counted_and_never_decoded() -> None:
    bus, _ = virtual(["radar-level@2"], faults=("slow=0.3@2",))
    dev = bus.engine.device(2)
    for name, value in {"air_gap_cm": 111, "air_gap_mm": 2222, "level_cm": 333}.items():
        dev.pin(name, value)

    async def go() -> list[object]:
        got: list[object] = []
        for address in range(3):
            try:
                got.append((await bus.read(2, Table.HOLDING, address, 1, timeout=0.1)).values[0])
            except DeviceTimeout:
                got.append("timeout")
        return got

    assert asyncio.run(go()) == [111, "timeout", 333]
    assert bus.unit_counts(2).late == 1


def test_the_scheduler_backs_off_a_dead_device_in_virtual_time() -> None:
    bus, clock = virtual(["radar-level@2", "huiwen-aq@3"], faults=("3:dead",))
    site = from_specs("virtual", [("radar-level", 2), ("huiwen-aq", 3)], baudrate=9600,
                      interval=1.0, timeout=0.2, check_serial=False)
    scheduler = Scheduler(site, open_bus=lambda _config: bus, clock=clock)

    async def go() -> None:
        poller = scheduler.buses[0]
        while clock.now < 120:  # what BusPoller.run does, with the waits passed virtually
            dev = poller.next_device()
            clock.now = max(clock.now, dev.next_due)
            await poller.run_one(dev, lambda dev, rs: None)

    asyncio.run(go())
    live, dead = scheduler.pollers()
    assert live.stats.state is State.ONLINE and live.stats.cycles >= 100
    assert dead.stats.state is State.OFFLINE
    assert dead.stats.timeouts < 15  # backed off: a probe now and then, not every second


def test_a_crc_error_is_known_at_once_not_after_the_timeout() -> None:
    """A complete reply with a bad CRC ends the attempt when it arrives: the retry goes
    after the silence, and the whole transaction costs far less than one timeout."""
    bus, clock = virtual(["radar-level@2"], faults=("2:crc@1",))

    async def go() -> tuple[int, ...]:
        return (await bus.read(2, Table.HOLDING, 2, 1, timeout=5.0, retries=1)).values

    asyncio.run(go())
    assert len(bus.sent) == 2  # the garbled attempt and its retry
    assert clock.now < 0.1  # not 5 s: the CRC error was known as it arrived


def test_a_crc_noisy_line_is_garbled_not_late_and_the_timeout_stays_put() -> None:
    """Issue 24.1 end to end through the scheduler, in virtual time: 30 % of the replies
    have a bad CRC. Garbled attempts are retried; not one reply is counted late; every
    value decoded is the pinned one; the learned timeout stays where a clean line puts it."""
    def run(faults: tuple[str, ...]) -> tuple[Scheduler, list[object]]:
        bus, clock = virtual(["radar-level@2", "huiwen-aq@3"], faults=faults)
        bus.engine.device(2).pin("level_cm", 333)
        site = from_specs("virtual", [("radar-level", 2), ("huiwen-aq", 3)], baudrate=9600,
                          interval=0.5, check_serial=False)
        scheduler = Scheduler(site, open_bus=lambda _config: bus, clock=clock)
        levels: list[object] = []

        def sink(dev: object, readings: list[Reading]) -> None:
            levels.extend(r.value.value for r in readings if r.value is not None
                          and r.field.name == "level_cm")

        async def go() -> None:
            poller = scheduler.buses[0]
            while clock.now < 60:
                dev = poller.next_device()
                clock.now = max(clock.now, dev.next_due)
                await poller.run_one(dev, sink)

        asyncio.run(go())
        return scheduler, levels

    clean, _ = run(())
    noisy, levels = run(("crc@30%",))
    assert levels and set(levels) == {333}
    for quiet, dev in zip(clean.pollers(), noisy.pollers(), strict=True):
        assert dev.stats.late == 0
        assert dev.stats.garbled + dev.stats.ok > 0
        assert dev.stats.timeout <= 1.5 * quiet.stats.timeout  # not climbing to 3 s


def test_an_echoing_adapter_and_crc_noise_in_virtual_time() -> None:
    """Issues 24.1 and 24.4 together: every request comes back first (the adapter), and
    30 % of the replies have a bad CRC. With echo on: every value decoded is right, no
    reply counted late. With echo off: every read says the adapter echoes."""
    config = build(["radar-level@2"], faults=("crc@30%",), seed=1, turnaround=0.002,
                   tick=None)
    clock = VirtualClock()
    engine = Engine(config.devices, config.faults, seed=1, tick=None)
    engine.device(2).pin("level_cm", 333)
    bus = VirtualBus(engine, clock=clock, sleep=clock.sleep, echo=True)

    async def go() -> list[object]:
        got: list[object] = []
        for _ in range(200):
            try:
                got.append((await bus.read(2, Table.HOLDING, 2, 1, timeout=0.1,
                                           retries=2)).values[0])
            except FrameError:
                got.append("garbled")
        return got

    got = asyncio.run(go())
    assert set(got) <= {333, "garbled"} and got.count(333) > 150
    assert bus.unit_counts(2).late == 0
    assert bus.stats.outcomes["ok"] == got.count(333)

    plain = VirtualBus(Engine(config.devices, (), seed=1, tick=None), clock=clock,
                       sleep=clock.sleep)
    plain.echo = True  # the adapter echoes, but the line was not told
    with pytest.raises(FrameError, match="--echo"):
        asyncio.run(plain.read(2, Table.HOLDING, 2, 1, timeout=0.1))
