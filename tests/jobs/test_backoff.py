"""The one backoff rule (``rtupoll.backoff``) and the four places that wait by it, with
the figures their documents give: a device with no valid reply (docs/polling.md), a
port that went away (docs/polling.md), a unit the gateway does not poll
(docs/gateway.md), the MQTT broker (docs/mqtt.md). Time is virtual or given."""

from __future__ import annotations

import asyncio

import pytest
from virtual import START, ScriptedBus, VirtualClock

from rtupoll.backoff import after_failures
from rtupoll.config.site import BusConfig, from_specs
from rtupoll.errors import PortError
from rtupoll.gateway.server import SilentUnits
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.outputs.mqtt import backoff as mqtt_backoff
from rtupoll.rtu import Table
from rtupoll.rtu.transaction import ReadResult


def test_the_rule_doubles_from_the_first_wait_up_to_the_cap() -> None:
    waits = [after_failures(n, first=0.5, cap=30.0) for n in range(1, 10)]
    assert waits == [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 30.0]
    assert after_failures(0, first=0.5, cap=30.0) == 0.5  # no failure counts as the first
    assert after_failures(3, first=1.0, cap=100.0, factor=3.0) == 9.0


def test_the_jitter_scales_the_wait_within_its_bounds_and_never_overflows() -> None:
    low = after_failures(2, first=1.0, cap=60.0, jitter=0.2, rand=lambda: 0.0)
    mid = after_failures(2, first=1.0, cap=60.0, jitter=0.2, rand=lambda: 0.5)
    high = after_failures(2, first=1.0, cap=60.0, jitter=0.2, rand=lambda: 0.999999)
    assert (low, mid) == (pytest.approx(1.6), 2.0) and 2.0 < high < 2.4
    # a device dead for years: the cap, not an OverflowError
    assert after_failures(10**9, first=1.0, cap=60.0) == 60.0


def test_a_devices_backoff_is_the_rule_from_its_interval() -> None:
    b = Backoff()  # docs/polling.md: max(1 s, interval) * 2^(n-1), capped at 60 s, ±20 %
    assert [b.delay(n, 0.5, lambda: 0.5) for n in (1, 2, 3, 7, 8)] == [1, 2, 4, 60, 60]
    assert b.delay(2, 5.0, lambda: 0.5) == 10.0
    assert b.delay(1, 1.0, lambda: 0.0) == pytest.approx(0.8)


class PortGone(ScriptedBus):
    """A bus whose adapter was unplugged: every read fails at once for the port."""

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        self.calls.append((unit, address, retries))
        raise PortError("/dev/ttyUSB0: the port is gone")


def test_a_bus_whose_port_went_away_pauses_1_2_4_8_then_10_seconds() -> None:
    clock = VirtualClock(START)
    config = from_specs("/dev/null", [("huiwen-aq", 3)], interval=0.5).buses[0]
    bp = BusPoller(BusConfig("b", "/dev/null", 9600, devices=config.devices),
                   PortGone(clock), backoff=Backoff(), clock=clock, wall=clock)
    dev = bp.devices[0]
    pauses = []
    for _ in range(7):
        clock.now = max(clock.now, dev.next_due)
        before = clock.now
        asyncio.run(bp.run_one(dev, lambda d, rs: None))
        pauses.append(dev.next_due - before)
    assert pauses == [1, 2, 4, 8, 10, 10, 10]
    assert dev.stats.failures == 0  # no device is blamed for the port


def test_a_unit_the_gateway_does_not_poll_is_held_1_2_4_up_to_30_seconds() -> None:
    silent = SilentUnits()  # docs/gateway.md: after three timeouts, 1 s, 2, 4 ... 30 s
    now, holds = 0.0, []
    for _ in range(9):
        silent.timed_out(7, now)
        end = now
        while silent.held(7, end):
            end += 0.25
        holds.append(end - now)
        now = end  # the probe after the hold times out too
    assert holds == [0, 0, 1, 2, 4, 8, 16, 30, 30]
    silent.answered(7)
    assert not silent.held(7, now)


def test_mqtt_reconnects_after_half_a_second_doubling_to_30() -> None:
    # docs/mqtt.md: 0.5, 1, 2, 4 ... s, capped at 30 s, ±20 %
    assert [mqtt_backoff(n, lambda: 0.5) for n in range(1, 9)] == \
        [0.5, 1, 2, 4, 8, 16, 30, 30]
    assert mqtt_backoff(1, lambda: 0.0) == pytest.approx(0.4)
