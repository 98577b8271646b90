"""Issue 24.4: adapters that echo (--echo, echo: true) and RS-485 direction control
(--rs485), end to end on the simulator's echoing adapter (direction control's modem-line
calls on a fake port: tests/io/test_rs485.py)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from cli_runner import rtupoll as in_process
from conftest import ANSWERED, PATIENT
from forked_cli import rtupoll_popen

from rtupoll.config.site import from_specs, load_site
from rtupoll.errors import ConfigError, DeviceTimeout, FrameError
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus, simulated_bus


@pytest.fixture
def echoing() -> Iterator[SimulatedBus]:
    """The huiwen and the radar behind an adapter that echoes every request."""
    bus = simulated_bus(["huiwen-aq@3", "radar-level@2"], tick=None)
    bus.echo = True
    bus.start()
    yield bus
    bus.stop()


def test_read_with_echo_reads_the_devices_values(echoing: SimulatedBus) -> None:
    result = in_process("read", "-p", echoing.port, *PATIENT, "--echo",
                        "radar-level@2", "--format", "json")
    assert result.returncode == 0, result.stderr
    records = [json.loads(line) for line in result.stdout.splitlines()]
    got = {r["field"]: r["raw"] for r in records}
    assert got["level_cm"] == list(echoing.registers(2, Table.HOLDING, 2, 1))


def test_read_without_echo_says_in_one_line_to_add_it(echoing: SimulatedBus) -> None:
    result = in_process("read", "-p", echoing.port, *PATIENT, "radar-level@2",
                        "--retries", "0")
    assert result.returncode == 7  # garbled, never a value
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "adapter echoes" in lines[0] and "--echo" in lines[0]


def test_echo_on_a_line_without_an_echo_is_said_too(sim: Any) -> None:
    plain = sim("radar-level@2", tick=None)
    result = in_process("read", "-p", plain.port, *PATIENT, "--echo",
                        "radar-level@2", "--retries", "0")
    assert result.returncode == 7 and "drop --echo" in result.stderr


def test_a_write_to_a_dead_device_is_never_confirmed_by_its_echo(
        echoing: SimulatedBus) -> None:
    async def go(echo: bool) -> list[str]:
        seen = []
        async with Bus(PortSettings(echoing.port, baudrate=9600, echo=echo)) as bus:
            # (a wait that something ends -- an echo, the radar's answer -- gets all the time
            # a busy machine's simulator thread may need: it ends when that comes)
            if not echo:  # an echo seen on a read first: the write's echo is known too
                with pytest.raises(FrameError):
                    await bus.read(2, Table.HOLDING, 2, 1, timeout=ANSWERED)
            for unit in (9, 2):  # 9: nobody there; 2: the radar
                # only unit 9 behind the echoing adapter (its echo consumed) must time out
                timeout = 0.2 if echo and unit == 9 else ANSWERED
                try:
                    await bus.write_registers(unit, 0x0010, [7], function=6, timeout=timeout)
                    seen.append("confirmed")
                except (DeviceTimeout, FrameError) as exc:
                    seen.append(type(exc).__name__)
                except Exception as exc:
                    seen.append(type(exc).__name__)
        return seen

    with_echo = asyncio.run(go(True))
    assert with_echo[0] == "DeviceTimeout"  # only its echo came back: no confirmation
    assert with_echo[1] != "DeviceTimeout"  # the radar's own answer (echo or exception)
    without = asyncio.run(go(False))
    assert without[0] == "FrameError"  # the echo is named, not taken for the reply


@pytest.fixture
def echoing_at_9600() -> Iterator[SimulatedBus]:
    """The same behind an echoing adapter at the wire timing of 9600 baud: each byte of a
    request comes back as it leaves the wire, one character time after the one before."""
    bus = simulated_bus(["huiwen-aq@3", "radar-level@2"], tick=None, baudrate=9600)
    bus.echo = True
    bus.start()
    yield bus
    bus.stop()


def requests_seen(bus: SimulatedBus) -> int:
    return sum(1 for w in bus.wire if w.direction == "in" and w.note.startswith("unit "))


def test_a_byte_paced_echo_is_named_on_the_first_request(echoing_at_9600: SimulatedBus
                                                          ) -> None:
    result = in_process("read", "-p", echoing_at_9600.port, "--baudrate",
                        "9600", "radar-level@2")  # the profile's retries
    assert result.returncode == 7, result.stderr  # garbled, never a value
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "adapter echoes" in lines[0] and "add --echo" in lines[0]
    assert "tries" not in lines[0] and requests_seen(echoing_at_9600) == 1  # no retry


def test_poll_carries_on_with_a_byte_paced_echo_and_says_so_once(
        echoing_at_9600: SimulatedBus) -> None:
    devices = ["huiwen-aq@3", "radar-level@2"]
    result = in_process("poll", "-p", echoing_at_9600.port, "--baudrate",
                        "9600", *PATIENT, *devices, "--once", "--format",
                        "json")
    assert result.returncode == 0, result.stderr
    records = [json.loads(line) for line in result.stdout.splitlines()]
    assert records and all(r["status"] == "ok" for r in records)
    assert result.stderr.count("adapter echoes") == 1 and "--echo" in result.stderr
    blind = requests_seen(echoing_at_9600)
    result = in_process("poll", "-p", echoing_at_9600.port, "--baudrate",
                        "9600", *PATIENT, *devices, "--once", "--echo")
    assert result.returncode == 0 and "adapter echoes" not in result.stderr
    assert blind == requests_seen(echoing_at_9600) - blind  # no request more than with --echo


def test_polled_with_a_byte_paced_echo_nothing_is_late_and_no_timeout_climbs(
        echoing_at_9600: SimulatedBus) -> None:
    site = from_specs(echoing_at_9600.port, [("huiwen-aq", 3), ("radar-level", 2)],
                      baudrate=9600)
    scheduler = Scheduler(site)

    async def go() -> None:
        await scheduler.open()
        try:
            for _ in range(5):
                await scheduler.scan_once(lambda dev, rs: None)
        finally:
            await scheduler.close()

    asyncio.run(go())
    for dev in scheduler.pollers():
        st = dev.stats
        assert st.ok == st.requests and st.late == 0 and st.timed_out == 0, st
        # learned from the device's reply times: at most its profile's, never climbing
        assert st.timeout is not None and st.timeout <= dev.config.profile.limits.timeout


def test_poll_simulate_with_echo_reads_every_field() -> None:
    result = in_process("poll", "--simulate", "huiwen-aq@3", "radar-level@2",
                        *PATIENT, "--echo", "--once", "--format", "json")
    assert result.returncode == 0, result.stderr
    records = [json.loads(line) for line in result.stdout.splitlines()]
    assert records and all(r["status"] == "ok" for r in records)


def test_poll_with_echo_through_the_gateway_answers_clients(echoing: SimulatedBus) -> None:
    """The bus consumes the echo for the gateway's clients' requests too."""
    async def go() -> bytes:
        async with Bus(PortSettings(echoing.port, baudrate=9600, echo=True)) as bus:
            return await bus.transact(2, bytes((3, 0, 2, 0, 1)), timeout=ANSWERED)

    pdu = asyncio.run(go())
    assert pdu[:2] == bytes((3, 2))
    assert int.from_bytes(pdu[2:4], "big") == echoing.registers(2, Table.HOLDING, 2, 1)[0]


# -- the site file -------------------------------------------------------------------


def _site(tmp_path: Path, extra: str) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n" + extra +
                    "    devices:\n      - profile: radar-level\n        address: 2\n")
    return path


def test_site_file_echo_and_rs485(tmp_path: Path) -> None:
    site = load_site(_site(tmp_path, "    echo: true\n    rs485:\n"
                                     "      delay_before: 0.001\n      delay_after: 0.002\n"))
    bus = site.buses[0]
    assert bus.echo is True and bus.rs485 == (0.001, 0.002)
    plain = load_site(_site(tmp_path, "    rs485: true\n")).buses[0]
    assert plain.echo is False and plain.rs485 == (0.0, 0.0)


def test_site_file_rs485_delay_out_of_range_is_file_line_field(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        load_site(_site(tmp_path, "    rs485:\n      delay_before: 5\n"))
    text = str(exc.value)
    assert "site.yaml:5" in text and "delay_before" in text


def test_rs485_on_a_pty_is_a_port_error_in_one_line(echoing: SimulatedBus) -> None:
    """A pseudo-terminal has no RS-485 mode and no RTS line: exit 3, one line."""
    result = in_process("read", "-p", echoing.port, "--rs485", "radar-level@2",
                        "--rs485-delays", "0,0.5")
    assert result.returncode == 3
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "supports neither" in lines[0]


def test_rs485_option_values() -> None:
    bad = in_process("read", "-p", "/dev/null", "--rs485", "--rs485-delays",
                     "abc", "radar-level@2")
    assert bad.returncode == 2 and "BEFORE_MS" in bad.stderr
    gateway = in_process("read", "-p", "tcp://127.0.0.1:1", "--rs485",
                         "radar-level@2")
    assert gateway.returncode == 2 and "not a serial port" in gateway.stderr


def test_sniff_on_a_line_whose_master_adapter_echoes(tmp_path: Path) -> None:
    """The echo is the master adapter's, not the line's: a sniffer on the line (the
    simulator's tap) sees each request once and decodes every value, while rtupoll
    reads through the echoing adapter with --echo."""
    import select
    import signal
    import subprocess
    import sys

    tap = str(tmp_path / "tap")
    bus = simulated_bus(["radar-level@2"], tick=None, tap=tap)
    bus.echo = True
    bus.start()
    rtupoll = str(Path(sys.executable).with_name("rtupoll"))
    try:
        proc = rtupoll_popen([rtupoll, "sniff", "-p", tap, "-b", "9600", *PATIENT, "--format",
                                 "json", "radar-level@2"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        assert proc.stderr is not None
        assert "listening on" in proc.stderr.readline()
        read = in_process("read", "-p", bus.port, *PATIENT, "--echo", "radar-level@2",
                          "level_cm", "--format", "json")
        assert proc.stdout is not None
        first = ""  # the sniffer's record of that read (a hang guard, not a deadline)
        while not first.startswith("{") and select.select([proc.stdout], [], [], 30)[0]:
            first = proc.stdout.readline()
            if not first:
                break
        proc.send_signal(signal.SIGINT)
        out, _err = proc.communicate(timeout=10)
        out = first + out
    finally:
        bus.stop()
    assert read.returncode == 0, read.stderr
    level = bus.registers(2, Table.HOLDING, 2, 1)[0]
    assert json.loads(read.stdout.splitlines()[0])["raw"] == [level]
    seen = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert [(r["field"], r["status"], r["raw"]) for r in seen] == [("level_cm", "ok", [level])]


def test_scan_without_echo_finds_the_devices_behind_an_echoing_adapter(
        echoing_at_9600: SimulatedBus) -> None:
    # the simulator answers from a thread of this process: a reply wait with room for a
    # busy machine (an answer ends it; an unanswered read makes the device "unknown")
    result = in_process("scan", "-p", echoing_at_9600.port, "--baudrate", "9600",
                        "--addresses", "2-3", "--turnaround", "1.0",
                        "--format", "json")
    assert result.returncode == 0, result.stderr
    found = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(f["address"], f["profile"]) for f in found] == [(2, "radar-level"),
                                                            (3, "huiwen-aq")]
    assert result.stderr.count("adapter echoes") == 1 and "--echo" in result.stderr
