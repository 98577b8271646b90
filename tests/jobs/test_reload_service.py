"""The service path: a port that vanishes and returns, state-change logging, sd_notify.

A gateway (the simulator on TCP) that goes away and comes back shows in the logs
once each way and in the metrics (``rtupoll_bus_port_up``, ``_port_losses_total``);
a device that times out every scan is logged once; ``rtupoll poll`` under a
``NOTIFY_SOCKET`` says READY, pings the watchdog, RELOADING/READY on SIGHUP and
STOPPING at the end.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from forked_cli import rtupoll_popen
from virtual import START, simulated

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.outputs.metrics import SchedulerCollector
from rtupoll.sim.runner import SimulatedBus, simulated_bus
from rtupoll.ui.logs import JsonFormatter, StateLog
from tests.brokers import free_port


def messages(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records]


def test_a_gateway_that_goes_and_returns_is_logged_once_each_way_and_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    address = f"127.0.0.1:{free_port()}"
    first = simulated_bus(["huiwen-aq@3"], tcp=address).start()
    second: SimulatedBus | None = None
    site = from_specs(f"tcp://{address}", [("huiwen-aq", 3)], interval=0.05, fields=["co2"],
                      check_serial=False)
    scheduler = Scheduler(site)
    collector = SchedulerCollector(scheduler)
    states = StateLog()
    statuses: list[str] = []

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        statuses.append(readings[0].status)
        collector.observe(scheduler.buses[0], dev, readings)
        states.on_readings(dev, readings)

    def port_up() -> float:
        got = [s.value for m in collector.collect() for s in m.samples
               if s.name == "rtupoll_bus_port_up"]
        return got[0]

    async def until(done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while not done():
            assert time.monotonic() < deadline, statuses[-5:]
            await asyncio.sleep(0.02)

    async def main() -> None:
        nonlocal second
        stop = asyncio.Event()
        await scheduler.open()
        await states.start(scheduler)
        task = asyncio.create_task(scheduler.run(sink, stop))
        try:
            await until(lambda: statuses.count("ok") >= 2)
            assert port_up() == 1
            first.stop()
            await until(lambda: statuses[-2:] == ["port"] * 2)  # logged once, not twice
            assert port_up() == 0
            second = simulated_bus(["huiwen-aq@3"], tcp=address).start()
            n = len(statuses)
            await until(lambda: "ok" in statuses[n:])
            assert port_up() == 1
            assert not task.done()
        finally:
            stop.set()
            await task
            await scheduler.close()

    try:
        with caplog.at_level(logging.INFO, logger="rtupoll"):
            asyncio.run(main())
    finally:
        first.stop()
        if second is not None:
            second.stop()
    losses = [s.value for m in collector.collect() for s in m.samples
              if s.name == "rtupoll_bus_port_losses_total"]
    assert losses == [1]
    log = messages(caplog)
    lost = [m for m in log if "port lost" in m]
    assert len(lost) == 1 and lost[0].startswith(f"tcp://{address}: port lost: ")
    assert sum(1 for m in log if "port back" in m) == 1


async def scans_logged(scheduler: Scheduler, scans: int) -> None:
    """``scans`` scans of every device, each cycle handed to a ``StateLog``."""
    states = StateLog()
    await scheduler.open()
    await states.start(scheduler)
    try:
        for _ in range(scans):
            await scheduler.scan_once(states.on_readings)
    finally:
        await scheduler.close()


def test_a_device_failing_every_scan_is_logged_on_change_only(
        caplog: pytest.LogCaptureFixture) -> None:
    # in virtual time (tests/virtual.py): the 4 dead cycles cost their timeouts on the
    # virtual clock, not 4 s of waiting (the logging on the real path: the gateway above,
    # the late replies below)
    bus, clock = simulated(["huiwen-aq@3"], ["3:dead@3-6"])  # one read per cycle: 2 good,
    # 4 dead
    site = from_specs("virtual", [("huiwen-aq", 3)], fields=["co2"], timeout=0.5, retries=0,
                      check_serial=False)
    scheduler = Scheduler(site, open_bus=lambda _: bus, clock=clock)
    with caplog.at_level(logging.INFO, logger="rtupoll"):
        asyncio.run(scans_logged(scheduler, 9))
    assert clock.now - START >= 4 * 0.5  # the dead cycles were waited out (virtually)
    device = [r for r in caplog.records if getattr(r, "event", "") == "device"]
    assert [r.levelname for r in device] == ["WARNING", "INFO"]
    assert device[0].getMessage().startswith("huiwen-aq@3 on virtual: timeout: no reply")
    assert "answering again (timeout for" in device[1].getMessage()
    assert device[1].getMessage().endswith(", 4 cycles)")
    line = json.loads(JsonFormatter().format(device[0]))
    assert line["level"] == "warning" and line["device"] == "huiwen-aq@3"
    assert line["status"] == "timeout" and line["time"].endswith("Z")


def test_sd_notify_ready_watchdog_reload_stopping(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(30)  # a guard against a hang, not a timing claim
        env = {**os.environ, "NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}
        proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "--simulate",
                                 "huiwen-aq@3", "--format", "json"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
        got: list[str] = []

        def until(word: str) -> None:
            while not any(m.startswith(word) for m in got):
                got.append(sock.recv(4096).decode())

        try:
            until("READY=1")
            assert f"MAINPID={proc.pid}" in got[0]
            until("WATCHDOG=1")
            n = len(got)
            proc.send_signal(signal.SIGHUP)
            until("RELOADING=1")
            while not any(m.startswith("READY=1") for m in got[n:]):
                got.append(sock.recv(4096).decode())
        finally:
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=20)
        until("STOPPING=1")
    assert code == 0
    assert got.index(next(m for m in got if m.startswith("RELOADING=1"))) < len(got) - 1


def test_late_replies_are_logged_once_and_counted_in_every_device_line(
        sim: Callable[..., SimulatedBus], caplog: pytest.LogCaptureFixture) -> None:
    bus = sim("radar-level@2", faults=["slow=0.3@2", "slow=0.3@5"], tick=None)
    site = from_specs(bus.port, [("radar-level", 2)], timeout=0.1, retries=0)
    scheduler = Scheduler(site)
    with caplog.at_level(logging.INFO, logger="rtupoll"):
        asyncio.run(scans_logged(scheduler, 4))
    late = [r for r in caplog.records if getattr(r, "status", "") == "late"]
    assert len(late) == 1  # logged once, though two replies came late
    line = json.loads(JsonFormatter().format(late[0]))
    assert line["device"] == "radar-level@2" and line["late"] >= 1
    assert scheduler.pollers()[0].stats.late >= 2
