"""SIGHUP applies a changed ``serve:``: the real ``rtupoll poll -c`` on the simulator,
mbpoll (``-m tcp``) as the other master. New rules take effect on the same listener, a
new address is re-bound, and an address that cannot be bound refuses the reload in one
line (the old listener and its rules go on); never "nothing changed"."""

from __future__ import annotations

import asyncio
import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import ANSWERED
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port, listening

MBPOLL = shutil.which("mbpoll")
pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed")


def site(path: Path, port: str, listen: str, **rules: object) -> None:
    text = (f"buses:\n  - port: {port}\n    baudrate: 9600\n"
            f"    serve:\n      listen: {listen}\n")
    text += "".join(f"      {k}: {json.dumps(v)}\n" for k, v in rules.items())
    # (a device that answers: ANSWERED, rtupoll's and mbpoll's)
    text += ("    devices:\n      - {name: gas, profile: net-irnet-pro, address: 1, "
             f"interval: 0.5, timeout: {ANSWERED:g}}}\n")
    path.write_text(text)


def mbpoll(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    assert MBPOLL is not None
    return subprocess.run([MBPOLL, "-m", "tcp", "-p", str(port), "-1", "-o", f"{ANSWERED:g}",
                           "-a", "1", *args], capture_output=True, text=True, timeout=60)


def test_sighup_applies_serve_rules_rebinds_and_refuses_an_address_it_cannot_bind(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    path, errors = tmp_path / "site.yaml", tmp_path / "stderr"
    first, second = free_port(), free_port()
    site(path, bus.port, f"127.0.0.1:{first}")
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "-c", str(path),
                             "--format", "json", "--log-format", "json"],
                            stdout=subprocess.DEVNULL, stderr=errors.open("w"))

    def log() -> list[str]:
        return [json.loads(x)["message"] for x in errors.read_text().splitlines()
                if x.startswith("{")]

    def wait(done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while not done():
            assert proc.poll() is None, errors.read_text()
            assert time.monotonic() < deadline, errors.read_text()
            time.sleep(0.05)

    def reload() -> list[str]:
        before = len([m for m in log() if m.startswith("reload")])
        proc.send_signal(signal.SIGHUP)
        wait(lambda: len([m for m in log() if m.startswith("reload")]) > before)
        time.sleep(0.2)  # the reload's other lines
        return [m for m in log() if m.startswith("reload")][before:]

    write = ("-t", "4:hex", "-r", "513", "127.0.0.1", "0x0000", "0x4248")  # gas level
    try:
        wait(lambda: listening(first))
        assert mbpoll(first, *write).returncode == 0

        site(path, bus.port, f"127.0.0.1:{first}", read_only=True)
        lines = reload()
        assert any("read_only false -> true" in x for x in lines), lines
        assert not any("nothing changed" in x for x in lines)
        refused = mbpoll(first, *write)
        assert refused.returncode != 0 and "Illegal function" in refused.stdout + \
            refused.stderr, refused.stdout + refused.stderr
        assert mbpoll(first, "-t", "4", "-r", "513", "-c", "2", "127.0.0.1").returncode == 0

        site(path, bus.port, f"127.0.0.1:{first}", read_only=True, allow=["10.0.0.0/8"])
        assert any("allow" in x for x in reload())
        assert mbpoll(first, "-t", "4", "-r", "513", "-c", "2", "127.0.0.1").returncode != 0

        site(path, bus.port, f"127.0.0.1:{second}")
        lines = reload()
        assert any(f"serving tcp://127.0.0.1:{second}" in x for x in lines), lines
        assert mbpoll(second, *write).returncode == 0
        assert not listening(first)

        with socket.socket() as taken:  # someone else holds the next address
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            busy = taken.getsockname()[1]
            site(path, bus.port, f"127.0.0.1:{busy}", read_only=True)
            lines = reload()
            assert len(lines) == 1 and lines[0].startswith("reload refused"), lines
            assert f"cannot serve tcp://127.0.0.1:{busy}" in lines[0]
        assert mbpoll(second, *write).returncode == 0  # the old listener, its old rules
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert proc.returncode == 0, errors.read_text()


def serve_site(path: Path, port: str, serve: str | None) -> Path:
    text = f"buses:\n  - port: {port}\n    baudrate: 9600\n"
    text += f"    serve: {serve}\n" if serve else ""
    text += "    devices:\n      - {name: gas, profile: net-irnet-pro, address: 1, " \
        "interval: 0.2}\n"
    path.write_text(text)
    return path


def test_a_serve_that_is_gone_stops_and_one_added_without_a_gateway_needs_a_restart(
        sim: Callable[..., SimulatedBus], tmp_path: Path,
        caplog: pytest.LogCaptureFixture) -> None:
    from rtupoll.config.site import load_site
    from rtupoll.gateway.service import GatewayService
    from rtupoll.jobs.reload import ReloadService
    from rtupoll.jobs.scheduler import Scheduler

    bus = sim("net-irnet-pro@1", tick=None)
    path, port = tmp_path / "site.yaml", free_port()

    async def main() -> tuple[bool, bool]:
        scheduler = Scheduler(load_site(serve_site(path, bus.port, f"127.0.0.1:{port}")))
        gateways = GatewayService()
        reload = ReloadService(lambda: load_site(path), peers=[gateways], serves=True)
        await scheduler.open()
        await gateways.start(scheduler)
        await reload.start(scheduler)
        try:
            was = listening(port)
            serve_site(path, bus.port, None)
            await reload.reload_once()
            gone = not listening(port) and gateways.gateways == []
        finally:
            await reload.stop()
            await gateways.stop()
            await scheduler.close()

        plain = Scheduler(load_site(serve_site(path, bus.port, None)))
        without = ReloadService(lambda: load_site(path), peers=[])
        await plain.open()
        await without.start(plain)
        try:
            serve_site(path, bus.port, f"127.0.0.1:{port}")
            await without.reload_once()
        finally:
            await without.stop()
            await plain.close()
        return was, gone

    with caplog.at_level("INFO", logger="rtupoll.reload"):
        was, gone = asyncio.run(main())
    assert was and gone
    lines = [r.getMessage() for r in caplog.records if r.name == "rtupoll.reload"]
    assert f"reload: bus {bus.port}: no longer serving tcp://127.0.0.1:{port}" in lines
    assert lines[-1].startswith("reload refused, polling goes on unchanged: serve: on ")
    assert "needs a restart" in lines[-1]
    assert not any("nothing changed" in x for x in lines)
