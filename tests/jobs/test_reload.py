"""SIGHUP: the site file reloaded while polling goes on, and the output file reopened.

In-process tests drive ``Scheduler.reload`` and the ``ReloadService`` against
simulated buses (the ports that do not change must stay open: the same port
object before and after); the last test sends real SIGHUPs to ``rtupoll poll``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
from forked_cli import rtupoll_popen

from rtupoll.config.site import load_site
from rtupoll.jobs.reload import ReloadService
from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.sim.runner import SimulatedBus

# the two devices most tests poll, as site-file entries
AIR = "{name: air, profile: huiwen-aq, address: 3, interval: 0.05, fields: [co2]}"
TANK = "{name: tank, profile: radar-level, address: 4, interval: 0.05, fields: [level_cm]}"


def site_file(path: Path, *buses: tuple[str, list[str]]) -> Path:
    """``buses``: (port, device lines in flow style)."""
    text = "buses:\n"
    for port, devices in buses:
        text += f"  - port: {port}\n    baudrate: 9600\n    devices:\n"
        text += "".join(f"      - {d}\n" for d in devices)
    path.write_text(text)
    return path


def port_of(bp: BusPoller) -> object:
    """The bus's open port (pymodbus's transport): the same object means the port was
    never reopened."""
    return vars(bp.transport).get("_port")


class Run:
    """A scheduler running in the background of a test's event loop, counting cycles."""

    def __init__(self, scheduler: Scheduler) -> None:
        self.scheduler = scheduler
        self.cycles: Counter[str] = Counter()
        self.stop = asyncio.Event()
        self.task: asyncio.Task[None] | None = None

    def sink(self, dev: DevicePoller, readings: list[Reading]) -> None:
        self.cycles[dev.config.name] += 1

    async def __aenter__(self) -> Run:
        await self.scheduler.open()
        self.task = asyncio.create_task(self.scheduler.run(self.sink, self.stop))
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.stop.set()
        assert self.task is not None
        await self.task  # a bus task that crashed would raise here
        await self.scheduler.close()

    async def until(self, done: Callable[[], bool], limit: float = 20.0) -> None:
        deadline = time.monotonic() + limit  # a guard against a hang, not a timing claim
        while not done():
            assert self.task is not None and not self.task.done(), "polling stopped"
            assert time.monotonic() < deadline, f"not reached: {dict(self.cycles)}"
            await asyncio.sleep(0.02)

    async def more(self, name: str, n: int) -> None:
        target = self.cycles[name] + n
        await self.until(lambda: self.cycles[name] >= target)


def test_add_change_and_remove_devices_keep_the_port_open(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4")
    path = tmp_path / "site.yaml"

    async def main() -> None:
        scheduler = Scheduler(load_site(site_file(path, (bus.port, [AIR]))))
        async with Run(scheduler) as run:
            await run.more("air", 3)
            bp, port = scheduler.buses[0], port_of(scheduler.buses[0])
            poller = bp.devices[0]
            assert port is not None

            changes = await scheduler.reload(load_site(site_file(path, (bus.port, [AIR, TANK]))))
            assert changes == ["added tank (radar-level@4) on " + bus.port]
            await run.more("tank", 3)
            await run.more("air", 3)  # the first device never stopped
            assert scheduler.buses == [bp] and bp.devices[0] is poller  # its state kept
            assert port_of(bp) is port  # the port was not reopened

            slow = AIR.replace("interval: 0.05", "interval: 30")
            changes = await scheduler.reload(load_site(site_file(path, (bus.port, [slow, TANK]))))
            assert changes == ["air: interval 0.05 s -> 30 s"]
            await run.more("air", 1)  # at most the one already due
            before = run.cycles["air"]
            await run.more("tank", 5)
            assert run.cycles["air"] == before  # now due only every 30 s
            assert bp.devices[0] is poller and poller.config.interval == 30

            changes = await scheduler.reload(load_site(site_file(path, (bus.port, [slow]))))
            assert changes == [f"removed tank from {bus.port}"]
            await asyncio.sleep(0.05)  # a cycle in flight may still finish
            after = run.cycles["tank"]
            await asyncio.sleep(0.3)
            assert run.cycles["tank"] == after
            assert [d.config.name for d in scheduler.pollers()] == ["air"]
            assert port_of(bp) is port

    asyncio.run(main())


def test_buses_come_and_go_while_the_others_poll(sim: Callable[..., SimulatedBus],
                                                 tmp_path: Path) -> None:
    one, two = sim("huiwen-aq@3"), sim("radar-level@4")
    path = tmp_path / "site.yaml"

    async def main() -> None:
        scheduler = Scheduler(load_site(site_file(path, (one.port, [AIR]))))
        async with Run(scheduler) as run:
            await run.more("air", 2)
            first = scheduler.buses[0]
            changes = await scheduler.reload(load_site(site_file(
                path, (one.port, [AIR]), (two.port, [TANK]))))
            assert changes == [f"opened bus {two.port} ({two.port}, 9600 8N1): 1 device"]
            await run.more("tank", 3)
            await run.more("air", 3)
            assert scheduler.buses[0] is first

            changes = await scheduler.reload(load_site(site_file(path, (two.port, [TANK]))))
            assert changes == [f"closed bus {one.port} ({one.port})"]
            assert port_of(first) is None  # closed
            after = run.cycles["air"]
            await run.more("tank", 5)
            assert run.cycles["air"] == after

    asyncio.run(main())


def test_a_broken_file_keeps_the_running_configuration(
        sim: Callable[..., SimulatedBus], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bus = sim("huiwen-aq@3")
    path = tmp_path / "site.yaml"
    site_file(path, (bus.port, [AIR]))

    async def main() -> None:
        scheduler = Scheduler(load_site(path))
        service = ReloadService(lambda: load_site(path))
        async with Run(scheduler) as run:
            await service.start(scheduler)
            await run.more("air", 2)
            path.write_text(path.read_text().replace("address: 3", "adress: 3"))
            with caplog.at_level(logging.INFO, logger="rtupoll"):
                await service.reload_once()
            await run.more("air", 3)  # still polling, as before
            assert [d.config.name for d in scheduler.pollers()] == ["air"]
            await service.stop()

    asyncio.run(main())
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1
    assert errors[0].startswith(f"reload refused, polling goes on unchanged: {path}:5: ")
    assert "adress" in errors[0]


@pytest.mark.parametrize("before", [signal.SIG_IGN, signal.SIG_DFL], ids=["nohup", "default"])
def test_sighup_does_what_it_did_before_once_the_service_stops(
        sim: Callable[..., SimulatedBus], tmp_path: Path, before: signal.Handlers) -> None:
    """Under ``nohup`` (SIGHUP ignored) a hang-up reloads while the service runs, and is
    ignored again afterwards: the loop's removal alone would leave the default, which
    ends the process."""
    bus = sim("huiwen-aq@3")
    path = site_file(tmp_path / "site.yaml", (bus.port, [AIR]))
    seen: list[object] = []

    async def main() -> None:
        scheduler = Scheduler(load_site(path))
        service = ReloadService(lambda: load_site(path))
        async with Run(scheduler):
            await service.start(scheduler)
            seen.append(signal.getsignal(signal.SIGHUP))
            await service.stop()

    was = signal.signal(signal.SIGHUP, before)
    try:
        asyncio.run(main())
        assert seen[0] not in (signal.SIG_IGN, signal.SIG_DFL)  # the loop's, meanwhile
        assert signal.getsignal(signal.SIGHUP) == before
    finally:
        signal.signal(signal.SIGHUP, was)


def test_with_no_sighup_as_on_windows_polling_runs_and_nothing_is_reloaded(
        sim: Callable[..., SimulatedBus], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Windows's ``signal`` has no SIGHUP: the service starts and stops without touching
    signals (no AttributeError), polling goes on, and the handler is never installed."""
    from rtupoll.jobs import reload

    monkeypatch.setattr(reload, "HANGUP", None)
    bus = sim("huiwen-aq@3")
    path = site_file(tmp_path / "site.yaml", (bus.port, [AIR]))
    seen: list[object] = []

    async def main() -> None:
        scheduler = Scheduler(load_site(path))
        service = ReloadService(lambda: load_site(path))
        async with Run(scheduler) as run:
            await service.start(scheduler)
            seen.append(signal.getsignal(signal.SIGHUP))
            await run.more("air", 2)
            await service.stop()

    was = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        asyncio.run(main())
    finally:
        signal.signal(signal.SIGHUP, was)
    assert seen == [signal.SIG_DFL]  # never the loop's handler


def on_a_terminal_that_hangs_up(tmp_path: Path, *, nohup: bool) -> tuple[bool, str]:
    """``rtupoll poll`` on a terminal of its own (a fresh process leading its session,
    the pty its controlling terminal, as a shell starts it: ``setsid --ctty``), which
    goes away once the table is shown: whether the command ended by itself, and its
    stderr."""
    import os
    import pty
    import select

    main, child = pty.openpty()
    was = signal.signal(signal.SIGHUP, signal.SIG_IGN if nohup else signal.SIG_DFL)
    try:  # (a disposition the child inherits)
        with (tmp_path / "stderr").open("w") as err:
            proc = subprocess.Popen(["setsid", "--ctty", sys.executable, "-m", "rtupoll",
                                     "poll", "--simulate", "huiwen-aq@3"],
                                    stdin=child, stdout=child, stderr=err)
    finally:
        signal.signal(signal.SIGHUP, was)
    os.close(child)
    shown, deadline = b"", time.monotonic() + 60  # guards against a hang, not timing claims
    while b"online" not in shown and time.monotonic() < deadline:
        if select.select([main], [], [], 0.1)[0]:
            shown += os.read(main, 65536)
    os.close(main)  # the window closed, the SSH session dropped
    try:
        proc.wait(timeout=1 if nohup else 30)
        return True, (tmp_path / "stderr").read_text()
    except subprocess.TimeoutExpired:
        proc.terminate()
        proc.wait()
        return False, (tmp_path / "stderr").read_text()


def test_poll_stops_when_its_terminal_hangs_up(tmp_path: Path) -> None:
    """Not a reload: a poll left running unseen would hold the port."""
    ended, err = on_a_terminal_that_hangs_up(tmp_path, nohup=False)
    assert ended, f"still polling 30 s after its terminal went away: {err}"
    assert "Traceback" not in err


def test_poll_under_nohup_outlives_its_terminal(tmp_path: Path) -> None:
    ended, err = on_a_terminal_that_hangs_up(tmp_path, nohup=True)
    assert not ended, err


def test_sighup_reloads_and_reopens_the_output(sim: Callable[..., SimulatedBus],
                                               tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4")
    path = tmp_path / "site.yaml"
    out = tmp_path / "readings.jsonl"
    air = "{name: air, profile: huiwen-aq, address: 3, interval: 0.1, fields: [co2]}"
    tank = "{name: tank, profile: radar-level, address: 4, interval: 0.1, fields: [level_cm]}"
    site_file(path, (bus.port, [air]))
    err = (tmp_path / "stderr").open("w")
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "-c", str(path),
                             "--format", "json", "-o", str(out), "--log-format", "json"],
                            stdout=subprocess.DEVNULL, stderr=err)

    def devices(file: Path) -> Counter[str]:
        if not file.exists():
            return Counter()
        text = file.read_text()
        whole = text[:text.rfind("\n") + 1]
        return Counter(json.loads(line)["device"] for line in whole.splitlines())

    def wait(done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while not done():
            assert proc.poll() is None, (tmp_path / "stderr").read_text()
            assert time.monotonic() < deadline, (tmp_path / "stderr").read_text()
            time.sleep(0.05)

    try:
        wait(lambda: devices(out)["air"] >= 2)
        site_file(path, (bus.port, [air, tank]))
        proc.send_signal(signal.SIGHUP)
        wait(lambda: devices(out)["tank"] >= 2)

        rotated = tmp_path / "readings.jsonl.1"
        out.rename(rotated)  # what logrotate does, then it sends SIGHUP
        path.write_text(path.read_text().replace("profile: radar-level", "profile: radarr"))
        proc.send_signal(signal.SIGHUP)
        wait(lambda: devices(out)["air"] >= 2 and devices(out)["tank"] >= 2)
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=20)
        err.close()
    log = [json.loads(line) for line in (tmp_path / "stderr").read_text().splitlines()]
    assert code == 0, log
    for file in (rotated, out):  # whole lines only, in both files
        text = file.read_text()
        assert text.endswith("\n")
        assert all(json.loads(line)["status"] for line in text.splitlines())
    events = [(e.get("event"), e["level"], e["message"]) for e in log]
    assert ("reload", "info", "reload: added tank (radar-level@4) on " + bus.port) in events
    refused = [m for ev, lvl, m in events if ev == "reload" and lvl == "error"]
    assert len(refused) == 1 and f"{path}:6: " in refused[0] and "radarr" in refused[0]
    assert sum(1 for ev, _, _ in events if ev == "reopen") == 2


def test_a_reload_hands_the_record_writer_the_new_site(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    """The records' bus tag follows a device moved to another bus: the reload calls the
    writer's ``follow`` (it owns its device -> bus names; nobody else holds them), and a
    refused reload changes nothing."""
    import io

    from rtupoll.outputs.influx import InfluxFormat
    from rtupoll.ui.record_writer import RecordWriter

    one, two = sim("huiwen-aq@3"), sim("huiwen-aq@3")
    path = site_file(tmp_path / "site.yaml", (one.port, [AIR]))
    out = io.StringIO()

    async def main() -> None:
        site = load_site(path)
        scheduler = Scheduler(site)
        writer = RecordWriter(out, InfluxFormat(site))
        service = ReloadService(lambda: load_site(path), writer)
        async with Run(scheduler) as run:
            await service.start(scheduler)
            await run.more("air", 1)
            writer.write(list(scheduler.pollers()[0].stats.latest.values()))
            site_file(path, (two.port, [AIR]))
            await service.reload_once()
            await run.more("air", 1)
            writer.write(list(scheduler.pollers()[0].stats.latest.values()))
            path.write_text("buses: [")  # refused: the tag stays
            await service.reload_once()
            writer.write(list(scheduler.pollers()[0].stats.latest.values()))
            await service.stop()

    asyncio.run(main())
    buses = [dict(t.split("=") for t in line.split(" ")[0].split(",")[1:])["bus"]
             for line in out.getvalue().splitlines() if line.startswith("rtupoll_status")]
    assert buses == [one.port, two.port, two.port]
