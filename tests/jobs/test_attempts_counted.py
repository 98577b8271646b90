"""Every attempt counted (issue 47: with 30 % of replies corrupted, 121 bad CRCs sent and
33 counted garbled): each request put on the wire is counted once by how it ended, and
a retry that was answered is counted too. In virtual time through the scheduler, the
line and the simulator's engine; then the real command on a pty, scraped at /metrics."""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from forked_cli import rtupoll_popen
from virtual import simulated

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.sim.engine import Transmission
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port
from tests.outputs.test_metrics import get, parse, scrape

DEVICES = ("huiwen-aq@3", "radar-level@2")


def test_garbled_counted_equals_garbled_sent_in_virtual_time() -> None:
    bus, clock = simulated(list(DEVICES), ["crc@30%", "3:dead@10,20,30"], baudrate=9600)
    sent: list[Transmission] = []
    handle = bus.engine.handle

    def counting(frame: bytes, now: float = 0.0, idle: float = float("inf")
                 ) -> list[Transmission]:
        out = handle(frame, now, idle)
        sent.extend(out)
        return out

    bus.engine.handle = counting  # type: ignore[method-assign]
    site = from_specs("virtual", [("huiwen-aq", 3), ("radar-level", 2)], baudrate=9600,
                      interval=0, check_serial=False)
    bp = BusPoller(site.buses[0], bus, backoff=Backoff(), clock=clock, wall=clock)

    async def go() -> None:
        end = clock.now + 30
        while clock.now < end:
            dev = bp.next_device()
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: None)

    asyncio.run(go())
    for dev in bp.devices:
        unit, st = dev.config.address, dev.stats
        crc = sum(1 for t in sent if t.unit == unit and "crc" in t.notes)
        assert crc >= 20 and st.garbled_attempts == crc, (dev.config.name, crc, st)
        # transactions only counted garbled when every attempt was: fewer
        assert st.garbled < crc
        # every request the engine saw for it was one attempt, answered or not
        answered = sum(1 for t in sent if t.unit == unit)
        assert st.attempts == answered + st.timed_out
        assert st.retried > 0 and st.retried <= st.ok
    huiwen = bp.devices[0].stats
    assert huiwen.timed_out == 3 > huiwen.timeouts  # deaf to three requests, each retried
    assert bp.transport.stats.attempts == sum(d.stats.attempts for d in bp.devices)


def test_on_a_pty_the_metrics_count_every_garbled_reply_the_simulator_sent(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim(*DEVICES, faults=["crc@30%"])
    port = free_port()
    err = (tmp_path / "stderr").open("w")
    proc = rtupoll_popen(
        [sys.executable, "-m", "rtupoll", "poll", "-p", bus.port, "--format", "json",
         "--interval", "0", "--metrics", f"127.0.0.1:{port}", *DEVICES],
        stdout=subprocess.DEVNULL, stderr=err)
    try:
        seen: list[tuple[float, int]] = []
        deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                samples = parse(scrape(port))
                counted = sum(get(samples, "rtupoll_attempts_total", bus=bus.port, device=d,
                                  outcome="garbled") or 0 for d in DEVICES)
                garbled_sent = sum(1 for w in bus.wire if w.direction == "out"
                                   and "crc" in w.note)
                seen.append((counted, garbled_sent))
                # never more counted than sent; a reply still on its way may be one short
                assert counted <= garbled_sent, seen
                if counted == garbled_sent >= 20:
                    break
            time.sleep(0.05)
        assert seen and seen[-1][0] == seen[-1][1] >= 20, seen
        retried = sum(get(samples, "rtupoll_retried_total", bus=bus.port, device=d) or 0
                      for d in DEVICES)
        assert retried > 0
    finally:
        proc.send_signal(2)
        proc.wait(timeout=30)
        err.close()
