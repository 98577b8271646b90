"""``rtupoll doctor``: every finding against the simulated adapter and device fault that
causes it (an echo paced byte by byte, an idle gap, pauses inside replies, a slow
device, a missing port), through the real command."""

from __future__ import annotations

import asyncio
import functools
import json
import types
from collections.abc import Callable
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.io.latency import latency_timer
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus, run
from rtupoll.jobs.doctor import Doctor, Finding
from rtupoll.jobs.doctor import _Heard as Heard
from rtupoll.sim.runner import SimulatedBus, simulated_bus

Sim = Callable[..., SimulatedBus]


def findings(*args: str) -> dict[str, dict[str, object]]:
    ran = rtupoll("doctor", "--format", "json", *args)
    assert ran.returncode == 0, ran.stderr
    return {r["check"]: r for r in map(json.loads, ran.stdout.splitlines())}


def test_a_quiet_adapter_and_a_healthy_device(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    got = findings("-p", bus.port, "-b", "9600", "huiwen-aq@3")
    assert got["port"]["status"] == "ok"
    assert got["echo"]["status"] == "ok" and "no echo" in str(got["echo"]["finding"])
    assert got["rs485"]["finding"].startswith("no kernel RS-485 mode")  # type: ignore[union-attr]
    assert got["idle-gap"]["status"] == "ok" and got["idle-gap"]["value"] == 0.0
    assert got["reply"]["status"] == "ok" and got["pauses"]["status"] == "ok"
    text = rtupoll("doctor", "-p", bus.port, "-b", "9600", "--address", "3")
    assert text.returncode == 0, text.stderr
    assert [line.split()[:2] for line in text.stdout.splitlines()[1:] if line[:1] != " "] == [
        ["ok", "port"], ["info", "latency"], ["info", "rs485"], ["ok", "echo"],
        ["ok", "idle-gap"], ["ok", "reply"], ["ok", "pauses"]]


def test_an_echo_that_comes_back_byte_by_byte_is_named_with_its_fix() -> None:
    # the master's 2-wire adapter hears itself, byte-paced at 2400 baud: 4.6 ms a byte
    bus = simulated_bus(["radar-level@2"], tick=None, baudrate=2400)
    bus.echo = True
    with bus:
        got = findings("-p", bus.port, "-b", "2400", "radar-level@2")
        with_echo = findings("-p", bus.port, "-b", "2400", "--echo")
    assert got["echo"]["status"] == "warning"
    assert "byte by byte" in str(got["echo"]["finding"]) and got["echo"]["fix"] == (
        "add --echo (echo: true on the bus in a site file)")
    assert got["reply"]["status"] == "ok"  # and the device's checks took the echo off
    assert with_echo["echo"]["status"] == "ok"


def test_an_echo_that_comes_back_at_once_is_said_so_after_three_probes() -> None:
    bus = simulated_bus(["radar-level@2"], tick=None)  # no wire timing: echoed at once
    bus.echo = True
    with bus:
        ran = rtupoll("doctor", "--format", "json", "-p", bus.port, "-b", "9600",
                      "--traffic", "--traffic-format", "json")
    assert ran.returncode == 0, ran.stderr
    echo = next(r for r in map(json.loads, ran.stdout.splitlines()) if r["check"] == "echo")
    assert "(all at once)" in echo["finding"]
    sent = [f for f in map(json.loads, ran.stderr.splitlines()) if f["direction"] == "tx"]
    assert [f["unit"] for f in sent] == [247, 247, 247]  # a late read looks at once too


def test_a_device_that_needs_an_idle_gap_gets_one_near_its_own(sim: Sim) -> None:
    # (0.2 s: a busy host's delays, tens of ms, do not make a 0.1 s trial look like 0.2)
    bus = sim("huiwen-aq@3", tick=None, faults=["3:gap=0.2"])
    got = findings("-p", bus.port, "-b", "9600", "huiwen-aq@3")
    assert got["idle-gap"]["status"] == "warning"
    assert got["idle-gap"]["value"] == 0.2  # the first tried that is not shorter than 200 ms
    assert got["idle-gap"]["fix"] == "give it idle_gap: 0.2 (--idle-gap 0.2)"
    assert got["reply"]["status"] == "ok"  # its reads after it kept the gap


def test_pauses_inside_replies_and_a_slow_device(sim: Sim) -> None:
    paused = sim("huiwen-aq@3", tick=None, baudrate=9600, faults=["3:pause=0.02"])
    got = findings("-p", paused.port, "-b", "9600", "huiwen-aq@3")
    assert got["pauses"]["status"] == "warning"
    assert float(got["pauses"]["value"]) >= 0.015  # type: ignore[arg-type]
    slow = sim("radar-level@2", tick=None, options=["radar-level@2.turnaround=0.28"])
    got = findings("-p", slow.port, "-b", "9600", "--timeout", "0.3", "radar-level@2")
    assert got["reply"]["status"] == "warning"  # within a fifth of the timeout
    assert float(got["reply"]["value"]) >= 0.24  # type: ignore[arg-type]
    assert str(got["reply"]["fix"]).startswith("give it a longer timeout (--timeout ")


def test_no_device_and_no_port(sim: Sim, tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    got = findings("-p", bus.port, "-b", "9600", "--address", "9", "--timeout", "0.1")
    assert got["reply"]["status"] == "problem" and "scan" in str(got["reply"]["fix"])
    missing = rtupoll("doctor", "-p", str(tmp_path / "ttyUSB9"))
    assert missing.returncode == 3
    assert missing.stderr.count("\n") == 1 and "does not exist" in missing.stderr


def test_a_usb_adapters_latency_timer_with_its_fix(sim: Sim, tmp_path: Path) -> None:
    dev = tmp_path / "sys/bus/usb-serial/devices/ttyUSB0"
    dev.mkdir(parents=True)
    (dev / "latency_timer").write_text("16\n")
    (tmp_path / "dev").mkdir()
    (tmp_path / "dev/ttyUSB0").write_text("")
    sysfs = functools.partial(latency_timer, root=str(tmp_path))
    bus = sim("huiwen-aq@3", tick=None)
    with SyncBus(PortSettings(port=bus.port)) as line:
        doc = Doctor(line, latency=lambda port: sysfs("/dev/ttyUSB0"))
        latency: Finding = run(doc.adapter())[0]
    assert (latency.status, latency.value) == ("warning", 0.016)
    assert latency.text == "the USB adapter's latency timer is 16 ms, added to every reply"
    assert "latency_timer" in latency.fix


def test_a_gap_trial_whose_silence_came_out_too_long_is_tried_again() -> None:
    """A trial of a 20 ms gap whose request went 60 ms after the last byte (a busy host)
    says nothing of 20 ms: tried again, it counts once its silence is under the next gap
    tried (50 ms); three too long, and the gap is not taken."""

    def trials(silences: list[float]) -> tuple[bool, int]:
        heard = Heard()
        asked = [0]
        now = [100.0]

        async def read(after: float) -> tuple[bool, list[tuple[float, bytes]]]:
            asked[0] += 1
            # the longer silence first (after + 0.1) as asked, then the trial's, scripted
            now[0] += after if after > 0.1 else silences.pop(0)
            heard.chunks.append((now[0], True, b"request"))
            now[0] += 0.01
            heard.chunks.append((now[0], False, b"reply"))
            return True, []

        holder = types.SimpleNamespace(heard=heard)
        got = asyncio.run(Doctor._answers_after(holder, read, 0.02, 0.05))  # type: ignore[arg-type]
        return got, asked[0]

    assert trials([0.06, 0.021]) == (True, 4)  # the first trial retried
    assert trials([0.06, 0.07, 0.08]) == (False, 6)  # never a fair trial: not taken
    assert trials([0.021]) == (True, 2)
