"""A device that needs an idle gap, polled beside a busy neighbour (issue 47: a Huiwen
module that ignores any request less than 50 ms after the last byte on the line, beside
a radar at --interval 0): in virtual time through the real scheduler, line and the
simulator's engine (tests/virtual.py), then on a pty through the real command."""

from __future__ import annotations

import asyncio
import dataclasses
import io
from typing import Any

import pytest
from rich.console import Console
from test_poll_faults import PollProcess
from virtual import VirtualClock, simulated

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.site import from_specs
from rtupoll.gateway.clients import ClientStats
from rtupoll.gateway.server import Gateway
from rtupoll.gateway.turns import Turns
from rtupoll.jobs.scheduler import BusPoller, Scheduler
from rtupoll.jobs.timeouts import CEILING
from rtupoll.outputs.metrics import SchedulerCollector
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import build
from rtupoll.sim.virtual import VirtualBus
from rtupoll.ui.live import PollView
from rtupoll.web.state import Clocks, health_state

NEEDS = 0.05  # the Huiwen's gap, seconds
SECONDS = 15.0


def poll_15s(gap: float | None) -> tuple[BusPoller, dict[str, int]]:
    """15 virtual seconds of both at --interval 0, at 9600 baud; ``gap``: the Huiwen's
    idle_gap as set (None: none set, learned)."""
    scheduler, clock = gap_site(gap)
    bp = scheduler.buses[0]

    async def go() -> None:
        end = clock.now + SECONDS
        while clock.now < end:
            dev = bp.next_device()
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: None)

    asyncio.run(go())
    return bp, {d.config.name: d.stats.ok for d in bp.devices}


def gap_site(gap: float | None) -> tuple[Scheduler, VirtualClock]:
    """The Huiwen that needs ``NEEDS`` beside the radar, on one virtual bus."""
    bus, clock = simulated(["huiwen-aq@3", "radar-level@7"], [f"3:gap={NEEDS}"],
                           baudrate=9600, turnaround=0.005)
    site = from_specs("virtual", [("huiwen-aq", 3), ("radar-level", 7)], baudrate=9600,
                      interval=0, check_serial=False)
    b = site.buses[0]
    if gap is not None:
        b = dataclasses.replace(b, devices=(dataclasses.replace(b.devices[0], idle_gap=gap),
                                            b.devices[1]))
    site = dataclasses.replace(site, buses=(b,))
    return Scheduler(site, open_bus=lambda _: bus, clock=clock), clock


def test_the_simulated_device_ignores_a_request_sooner_than_its_gap() -> None:
    config = build(["huiwen-aq@3"], faults=(f"3:gap={NEEDS}",), tick=None)
    engine = Engine(config.devices, config.faults, tick=None)
    request = ReadRequest(3, 4, 30009, 1).frame()
    assert engine.handle(request, 1.0, idle=0.049) == []
    assert "gap" in engine.why_silent and "50 ms" in engine.why_silent
    assert len(engine.handle(request, 2.0, idle=0.05)) == 1
    assert len(engine.handle(request, 3.0)) == 1  # (no idle given: a quiet line)


def test_a_gap_needing_device_beside_a_busy_one_gets_its_gap_learned() -> None:
    bp, ok = poll_15s(None)
    huiwen = bp.devices[0]
    assert isinstance(bp.transport, type(bp.transport))
    line = bp.transport.line  # type: ignore[attr-defined]
    assert NEEDS <= line.learned_gap[3] <= 4 * NEEDS
    # the learned timeout is the device's own (a few tens of ms), not the ceiling
    assert huiwen.timing.timeout < 0.2 < CEILING
    assert line.counts.late[3] == 0
    # before: 6 reads of the Huiwen against 130 of the radar (its timeout at 3 s)
    assert ok["huiwen-aq@3"] >= 30 and ok["radar-level@7"] >= 250, ok


def test_a_learned_gap_is_shown_in_the_footer_the_api_and_the_metrics() -> None:
    scheduler, clock = gap_site(None)

    async def go() -> None:
        bp = scheduler.buses[0]
        end = clock.now + SECONDS
        while clock.now < end:
            dev = bp.next_device()
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: None)

    asyncio.run(go())
    huiwen, radar = scheduler.pollers()
    health = health_state(huiwen, Clocks())
    assert health["idle_gap_source"] == "learned" and health["idle_gap"] >= NEEDS
    assert health["timed_out_attempts"] >= 2 and health["retried"] >= 2
    assert health_state(radar, Clocks())["idle_gap"] == 0.0
    samples = {(s.name, s.labels.get("device"), s.labels.get("source")): s.value
               for family in SchedulerCollector(scheduler, clock=clock).collect()
               for s in family.samples}
    assert samples["rtupoll_device_idle_gap_seconds", "huiwen-aq@3", "learned"] == \
        pytest.approx(health["idle_gap"])
    assert not [k for k in samples if k[0] == "rtupoll_device_idle_gap_seconds"
                and k[1] == "radar-level@7"]
    out = io.StringIO()
    Console(file=out, width=120, color_system=None).print(
        PollView(scheduler.buses, title="virtual").health_table(120))
    row = next(line for line in out.getvalue().splitlines() if "huiwen-aq@3" in line)
    assert f"~{health['idle_gap'] * 1000:.0f} ms" in row


def test_a_gap_set_costs_no_attempt_and_no_learning() -> None:
    bp, ok = poll_15s(NEEDS)
    line = bp.transport.line  # type: ignore[attr-defined]
    stats = bp.transport.stats
    assert stats is not None
    assert stats.attempts == stats.transactions  # no request went unheard
    assert line.learned_gap == {} and line.counts.gap_raised[3] == 0
    assert ok["huiwen-aq@3"] >= 100, ok


def scans(records: list[dict[str, Any]], device: str) -> int:
    field = {"huiwen-aq@3": "co2", "radar-level@7": "air_gap_cm"}[device]
    return sum(1 for r in records if r["device"] == device and r["field"] == field
               and r["status"] == "ok")


def test_on_a_pty_the_gap_needing_device_keeps_being_read_beside_a_busy_one() -> None:
    """The real command on the simulator, at the wire timing of 9600 baud. Before: one
    scan of the Huiwen against 17 of the radar in 15 s (its timeout at 3 s)."""
    p = PollProcess("--simulate", "huiwen-aq@3", "radar-level@7", "--fault",
                    f"3:gap={NEEDS}", "--baud", "9600", "--interval", "0")
    done = p.until(lambda rs: scans(rs, "radar-level@7") >= 40, limit=120)
    stderr, code = p.stop()
    assert done and code == 0, stderr
    huiwen, radar = scans(p.records, "huiwen-aq@3"), scans(p.records, "radar-level@7")
    assert huiwen * 8 >= radar, (huiwen, radar)  # measured: 12 against 43


HUIWEN_CO2 = bytes((4,)) + (30009).to_bytes(2, "big") + (1).to_bytes(2, "big")  # a PDU


@pytest.mark.parametrize("polled_first", [True, False], ids=["after-a-poll", "before-any"])
def test_a_gateway_request_to_the_device_keeps_its_gap(polled_first: bool) -> None:
    """A Modbus TCP client's request to the Huiwen right after the radar's reply waits
    for the Huiwen's gap and is heard (no retry, no timeout): after the poller's reads
    named the gap (the line keeps it for the unit), and before the poller has read the
    Huiwen once (the gateway names the polled device's gap itself,
    ``BusLike.transact(idle_gap=)``)."""
    scheduler, clock = gap_site(NEEDS)
    bp = scheduler.buses[0]
    huiwen, radar = bp.devices
    gw = Gateway(ServeConfig("127.0.0.1", 0), bp, Turns(), clock=clock)
    bus = bp.transport
    assert isinstance(bus, VirtualBus)

    async def go() -> list[bytes | None]:
        if polled_first:
            await bp.run_one(huiwen, lambda d, rs: None)  # its reads name the gap
        replies = []
        for _ in range(5):
            await bp.run_one(radar, lambda d, rs: None)
            replies.append(await gw.answer(3, HUIWEN_CO2, ClientStats("c")))
        return replies

    replies = asyncio.run(go())
    assert all(r is not None and r[0] == 4 for r in replies), replies  # answers, no 0x0B
    assert bus.stats.attempts == bus.stats.transactions  # none went unheard
    assert bus.line.learned_gap == {}
