"""A newcomer's first ten minutes: the demo is a bus that could exist, every hint the
tool prints works as printed, wrong speeds are named, values agree with each other."""

from __future__ import annotations

import asyncio
import dataclasses
import io
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_runner import Ran, rtupoll
from conftest import ANSWERED, dead_at
from forked_cli import rtupoll_popen
from rich.console import Console

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.sim.runner import SimulatedBus, SimulatedLines, simulated_lines
from rtupoll.sim.scenario import build, cannot_run, speeds, split_lines
from rtupoll.ui.live import PollView

BIN = Path(sys.executable).parent


@pytest.fixture
def demo() -> Iterator[SimulatedLines]:
    with simulated_lines(tick=None) as lines:
        yield lines


# -- the demo is a bus that could exist ---------------------------------------------

def test_the_demo_is_two_lines_each_at_a_speed_all_its_devices_run_at(
        demo: SimulatedLines) -> None:
    got = [(line.config.line_speed, [d.name for d in line.config.devices]) for line in demo]
    assert got == [
        (9600, ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "banner-ez-array@5"]),
        (115200, ["co2meter-an117@4"])]
    for line in demo:
        for d in line.config.devices:
            assert line.config.line_speed in speeds(d.profile), d.name


def test_named_devices_go_on_as_few_lines_as_their_speeds_allow() -> None:
    config = build(["huiwen-aq@3", "co2meter-an117@4", "net-irnet-pro@1"])
    lines = split_lines(config)
    assert [(c.speed, [d.name for d in c.devices]) for c in lines] == [
        (9600, ["net-irnet-pro@1", "huiwen-aq@3"]), (115200, ["co2meter-an117@4"])]
    timed = split_lines(dataclasses.replace(config, baudrate=19200), 19200)
    assert [(c.baudrate, c.speed) for c in timed] == [(19200, None), (115200, None)]
    one = build(["huiwen-aq@3", "co2meter-an117@4"], baudrate=9600)  # --baud: as asked
    assert cannot_run(one) == ["co2meter-an117@4 runs at 115200 only, not 9600"]


def test_simulate_prints_hints_that_work_as_printed() -> None:
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "simulate", "--tick", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out = _until(proc, "Press Ctrl-C to stop.")
        hints = out.split("Try:\n", 1)[1].split("Press Ctrl-C")[0].split("\n")
        hints = [h.strip() for h in hints if h.strip()]
        assert [h.split()[:2] for h in hints] == [
            ["rtupoll", "read"], ["rtupoll", "poll"], ["mbpoll", "-m"], ["rtupoll", "poll"]]
        assert all(" -b 9600 " in h for h in hints[:3]) and " -b 115200 " in hints[3]
        for hint in hints:
            words = hint.split()
            if words[:2] == ["rtupoll", "poll"]:
                words.append("--once")  # as printed, it polls until Ctrl-C
            if words[0] == "rtupoll":  # the command, in this process (tests/cli_runner.py)
                run: subprocess.CompletedProcess[str] | Ran = rtupoll(*words[1:])
            else:
                run = subprocess.run(words, capture_output=True, text=True, timeout=60,
                                     check=False)
            assert run.returncode == 0, f"{hint}\n{run.stdout}{run.stderr}"
            if words[0] == "mbpoll":
                assert re.search(r"^\[4\]:\s+0x[0-9A-F]{4}$", run.stdout, re.M), run.stdout
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=20)
    assert proc.returncode == 0


def _until(proc: subprocess.Popen[str], text: str) -> str:
    assert proc.stdout is not None
    seen, deadline = "", time.monotonic() + 30
    fd = proc.stdout.fileno()
    while text not in seen and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 1)
        if ready:
            chunk = os.read(fd, 4096).decode()
            assert chunk, seen
            seen += chunk
    assert text in seen, seen
    return seen


def test_poll_simulate_polls_the_demo_as_two_buses_all_online() -> None:
    run = rtupoll("poll", "--simulate", "--once", "--format", "json")
    assert run.returncode == 0, run.stderr
    records = [json.loads(line) for line in run.stdout.splitlines()]
    assert {r["device"] for r in records} == {
        "net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
        "banner-ez-array@5"}
    assert all(r["status"] == "ok" for r in records)


def test_poll_simulate_with_wire_timing_keeps_the_co2meter_on_its_own_line() -> None:
    run = rtupoll("poll", "--simulate", "--once", "--baud", "9600", "--fault", "3:dead")
    assert run.returncode == 9, run.stderr
    assert "huiwen-aq@3: timeout" in run.stderr and "1 of 5 devices failed" in run.stderr
    assert re.search(r"bus line1 .*9600 8N1", run.stdout)
    assert re.search(r"bus line2 .*115200 8N1", run.stdout)


# -- speeds: a line answers at its own, and a wrong one is named ----------------------

def test_a_line_without_wire_timing_answers_only_at_its_speed_and_the_error_says_so(
        demo: SimulatedLines) -> None:
    port = demo.lines[0].port
    wrong = rtupoll("read", "-p", port, "net-irnet-pro@1", "--timeout", "0.1")
    assert wrong.returncode == 4
    assert "at 4800 baud (net-irnet-pro's default)" in wrong.stderr
    assert f"find it with 'rtupoll scan -p {port}' or give --baudrate" in wrong.stderr
    assert len(wrong.stderr.strip().splitlines()) == 1
    right = rtupoll("read", "-p", port, "-b", "9600", "net-irnet-pro@1", "--format", "json")
    assert right.returncode == 0, right.stderr


def test_poll_once_on_a_silent_line_names_its_speed(demo: SimulatedLines) -> None:
    port = demo.lines[0].port
    run = rtupoll("poll", "-p", port, "-b", "19200", "--once", "--timeout", "0.1",
                  "--retries", "0", "radar-level@2")
    assert run.returncode == 9
    assert (f"rtupoll: nothing answered on {port} at 19200 8N1; if the devices run at "
            f"another speed, find it with 'rtupoll scan -p {port}' or give --baudrate"
            ) in run.stderr


# a scan's probes wait for the wire time and the devices' turnaround: on a loaded machine
# a simulator's thread answered a probe late, and the device was listed at the other
# speed only; a slow device's turnaround keeps what these tests show, whatever the load
PATIENT = ("--turnaround", "0.15")


def test_scan_of_a_demo_line_lists_each_device_once(demo: SimulatedLines) -> None:
    result = rtupoll("scan", "-p", demo.lines[0].port, "--format", "json",
                     "--addresses", "1-5", "--baudrate", "4800,9600",
                     *PATIENT)
    assert result.returncode == 0, result.stderr
    found = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(f["address"], f["baudrate"], f["profile"]) for f in found] == [
        (1, 9600, "net-irnet-pro"), (2, 9600, "radar-level"), (3, 9600, "huiwen-aq"),
        (5, 9600, "banner-ez-array")]


def test_scan_of_a_line_that_answers_any_speed_says_so_and_lists_each_once(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", "radar-level@2", tick=None)  # in-process: any speed
    result = rtupoll("scan", "-p", bus.port, "--format", "json",
                     "--addresses", "1-3", "--baudrate", "4800,9600",
                     *PATIENT)
    assert result.returncode == 0, result.stderr
    assert "answered at every baud rate scanned (4800, 9600)" in result.stderr
    found = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(f["address"], f["baudrate"]) for f in found] == [(2, 9600), (3, 9600)]


# -- consistent demo values ------------------------------------------------------------

def test_the_same_quantity_in_two_units_agrees_as_values_move(demo: SimulatedLines) -> None:
    line = demo.line_of(2)
    seen: set[tuple[str, int]] = set()
    for _ in range(5):
        line.advance(7)
        for name in ("air_gap", "level"):
            cm, mm = (line.get(2, f"{name}_{u}").value for u in ("cm", "mm"))
            assert isinstance(cm, int) and isinstance(mm, int)
            assert abs(mm - 10 * cm) <= 5, (name, cm, mm)
            seen.add((name, mm))
    assert len(seen) > 2  # the values did move


@pytest.mark.parametrize(("pm25", "level"), [(12, "EXCELLENT"), (60, "GOOD"),
                                              (130, "MODERATE"), (153, "SEVERE")])
def test_a_level_follows_its_reading(demo: SimulatedLines, pm25: int, level: str) -> None:
    line = demo.line_of(3)
    line.set(3, "pm25", pm25)
    assert line.get(3, "pm25_level").text == level


def test_configuration_says_the_lines_speed_and_stays_in_its_values(
        demo: SimulatedLines) -> None:
    line = demo.line_of(2)
    assert line.get(2, "baud_rate").value == 9600
    assert line.get(1, "uart_speed").text == "UART_9600"


def test_every_demo_value_is_inside_its_fields_values_and_range(
        demo: SimulatedLines, sim: Callable[..., SimulatedBus]) -> None:
    anyspeed = sim("radar-level@2", tick=None)  # no line speed: a value from the list
    assert anyspeed.get(2, "baud_rate").value in (9600, 19200, 38400, 57600, 115200)
    for line in demo:
        line.advance(20)
        for d in line.device_list():
            for f in d.fields:
                v = line.get(d.address, f.name).value
                if f.values:
                    assert v in f.values, (d.name, f.name, v)
                if f.range and isinstance(v, (int, float)):
                    assert f.minimum is not None and f.maximum is not None
                    assert f.minimum <= v <= f.maximum, (d.name, f.name, v)


# -- the live table ----------------------------------------------------------------------

def scanned(bus: SimulatedBus, devices: list[str], dead: tuple[int, ...] = ()) -> Scheduler:
    """One scan of ``devices``; those at the ``dead`` addresses are asked with ``DEAD``."""
    specs = [(d.split("@")[0], int(d.split("@")[1])) for d in devices]
    site = from_specs(bus.port, specs, baudrate=9600, timeout=ANSWERED, retries=0,
                      check_serial=False)
    scheduler = Scheduler(dead_at(site, dead))

    async def run() -> None:
        await scheduler.open()
        try:
            await scheduler.scan_once(lambda d, r: None)
        finally:
            await scheduler.close()

    asyncio.run(run())
    return scheduler


def show(view: PollView, width: int = 110, height: int = 60) -> list[str]:
    out = io.StringIO()
    Console(file=out, width=width, height=height, color_system=None).print(view)
    return out.getvalue().splitlines()


def test_the_tall_table_shows_severity_and_status_apart(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("radar-level@2", "huiwen-aq@3", faults=["2:dead"], tick=None)
    bus.set(3, "co2_level", "MODERATE")
    lines = show(PollView(scanned(bus, ["radar-level@2", "huiwen-aq@3"], dead=(2,)).buses,
                          title="t", live=False))
    head = [c.strip() for c in lines[1].split("┃")]
    assert head == ["device", "field", "value", "unit", "severity", "status"]
    cells = {c[1]: c for c in ([x.strip() for x in line.split("│")] for line in lines)
             if len(c) == 6}
    assert cells["co2_level"][2:] == ["MODERATE", "", "warning", "ok"]
    assert cells["air_gap_cm"][2:] == ["—", "cm", "", "timeout"]


def test_the_once_footer_has_no_load_figures_and_counts_in_words(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    lines = show(PollView(scanned(bus, ["huiwen-aq@3"]).buses, title="t", live=False))
    assert lines[0] == "t · 1/1 online · 1 scan"
    footer = next(line for line in lines if line.startswith("bus "))
    assert "busy" not in footer and "transactions/s" not in footer


def test_live_table_columns_do_not_shrink_when_a_value_gets_shorter(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    site = from_specs(bus.port, [("huiwen-aq", 3)], fields=["tvoc"], timeout=ANSWERED)
    scheduler = Scheduler(site)
    view = PollView(scheduler.buses, title="t", live=True)
    widths = []

    async def run() -> None:
        await scheduler.open()
        try:
            for tvoc in (49.875, 0.5):  # wider than the header, then narrower
                bus.set(3, "tvoc", tvoc)
                await scheduler.scan_once(lambda d, r: None)
                row = next(line for line in show(view) if " tvoc " in line)
                assert f"{tvoc:.3f} " in row  # one precision: the scale's, 0.001
                widths.append(len(row.split("│")[2]))  # the value column
        finally:
            await scheduler.close()

    asyncio.run(run())
    assert widths[0] == widths[1]


# -- messages ----------------------------------------------------------------------------

def test_poll_with_devices_and_no_port_asks_for_the_port() -> None:
    result = rtupoll("poll", "huiwen-aq@3", "--once", env={
        "RTUPOLL_PORT": ""})
    assert result.returncode == 2
    assert "which port is huiwen-aq@3 on? give --port PORT (or $RTUPOLL_PORT)" in \
        result.stderr


def test_read_without_a_port_mentions_the_environment_variable() -> None:
    result = rtupoll("read", "huiwen-aq@3", env={"RTUPOLL_PORT": ""})
    assert result.returncode == 2
    assert "$RTUPOLL_PORT" in result.stderr and len(result.stderr.splitlines()) == 1


def test_a_raw_write_is_headed_by_the_unit_it_went_to(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("radar-level@2", tick=None)
    result = rtupoll("write", "-p", bus.port, "--raw", "--yes", "2", "holding:0x03F6=192",
                     env={"COLUMNS": "100"})
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == "unit 2 after writing (read back)"
    assert bus.get(2, "baud_rate").value == 19200


# -- scripts/setup: what the first scripts/poll shows --------------------------------------

FAKE_PYTHON = """#!/usr/bin/env bash
# python3 -m venv DIR: a venv whose pip is noisy, and fails when asked to
mkdir -p "$3/bin"
cat > "$3/bin/pip" <<'PIP'
#!/usr/bin/env bash
echo "Collecting pymodbus"; echo "Installing collected packages: lots of noise"
[ -n "${FAIL_PIP:-}" ] && { echo "ERROR: no matching distribution"; exit 1; }
printf '#!/bin/sh\\n' > "$(dirname "$0")/rtupoll"; chmod +x "$(dirname "$0")/rtupoll"
PIP
printf '#!/bin/sh\\n' > "$3/bin/python"
chmod +x "$3/bin/pip" "$3/bin/python"
"""


def setup_copy(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    root = Path(__file__).parents[2]
    (tmp_path / "scripts").mkdir()
    (tmp_path / "scripts" / "setup").write_text((root / "scripts" / "setup").read_text())
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    fake = tmp_path / "fakebin"
    fake.mkdir()
    (fake / "python3").write_text(FAKE_PYTHON)
    (fake / "python3").chmod(0o755)
    return tmp_path, {**os.environ, "PATH": f"{fake}{os.pathsep}{os.environ['PATH']}"}


def test_setup_says_what_it_does_one_line_per_step_and_keeps_pip_quiet(
        tmp_path: Path) -> None:
    where, env = setup_copy(tmp_path)
    first = subprocess.run(["bash", "scripts/setup"], cwd=where, env=env,
                           capture_output=True, text=True, timeout=60, check=False)
    assert first.returncode == 0, first.stderr
    assert first.stdout == ""
    assert first.stderr.splitlines() == [
        "setup: creating the virtualenv .venv (python3 -m venv)",
        "setup: installing rtupoll into .venv (pip: the first time 15-60 s, by the network "
        "and the machine)",
        "setup: done: .venv/bin/rtupoll is ready (the installers' output: .venv/setup.log)"]
    assert "Collecting pymodbus" in (where / ".venv" / "setup.log").read_text()
    again = subprocess.run(["bash", "scripts/setup"], cwd=where, env=env,
                           capture_output=True, text=True, timeout=60, check=False)
    assert (again.returncode, again.stdout, again.stderr) == (0, "", "")


def test_setup_shows_the_installers_output_when_a_step_fails(tmp_path: Path) -> None:
    where, env = setup_copy(tmp_path)
    run = subprocess.run(["bash", "scripts/setup"], cwd=where, env={**env, "FAIL_PIP": "1"},
                         capture_output=True, text=True, timeout=60, check=False)
    assert run.returncode == 1
    lines = run.stderr.splitlines()
    assert lines[2].startswith("setup: failed: .venv/bin/pip install")
    assert lines[-1] == "ERROR: no matching distribution"


# -- issue 28: examples and hints that work as printed ----------------------------------

@pytest.mark.parametrize("command", [
    ["scan"], ["read", "huiwen-aq@3"], ["set-address", "huiwen-aq@3", "4", "--yes"],
    ["write", "net-irnet-pro@1", "calibration_gas_level=50", "--yes"]])
def test_every_command_takes_its_port_from_rtupoll_port_and_says_so(command: list[str]
                                                                   ) -> None:
    run = rtupoll(*command, env={"RTUPOLL_PORT": None})
    assert run.returncode == 2
    assert run.stderr.strip().endswith("or set $RTUPOLL_PORT")
    helped = rtupoll(command[0], "--help").stdout
    assert "$RTUPOLL_PORT" in helped and "[required]" not in helped


def test_the_closing_hint_of_a_simulated_poll_names_a_device_that_exists() -> None:
    import pty

    main, child = pty.openpty()
    proc = subprocess.Popen([str(BIN / "rtupoll"), "poll", "--simulate", "epever-tracer@2",
                             "eastron-sdm630@1"], stdout=child, stderr=subprocess.PIPE,
                            text=True)
    os.close(child)
    try:
        seen = b""
        deadline = time.monotonic() + 30
        while b"online" not in seen and time.monotonic() < deadline:
            if select.select([main], [], [], 1)[0]:
                seen += os.read(main, 65536)
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        os.close(main)
    assert proc.returncode == 0
    dead = re.search(r"Try --fault (\d+):dead", err)
    assert dead and int(dead.group(1)) in (1, 2), err


@pytest.mark.parametrize("extra", ["mqtt", "metrics", "web", "edge"])
def test_a_missing_librarys_hint_is_a_command_that_works_as_printed(extra: str) -> None:
    """The hint installs into the Python that runs rtupoll, from the index a user has
    (rtupoll itself is on none): run as printed (plus --dry-run, --no-index: this venv
    has the libraries), pip finds every requirement already satisfied."""
    import shlex

    from packaging.requirements import Requirement

    from rtupoll.errors import MissingLibrary, install_command

    names, command = install_command(extra)
    words = shlex.split(command)
    assert words[:4] == [sys.executable, "-m", "pip", "install"]
    wanted = [Requirement(w) for w in words[4:]]
    assert wanted and names == ", ".join(r.name for r in wanted)
    from importlib.metadata import version
    assert all(r.specifier.contains(version(r.name)) for r in wanted)
    ran = subprocess.run([*words, "--dry-run", "--no-index", "--disable-pip-version-check"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert ran.returncode == 0, ran.stderr
    assert all(f"Requirement already satisfied: {w} " in ran.stdout for w in words[4:]), \
        ran.stdout
    assert "Would install" not in ran.stdout, ran.stdout
    assert str(MissingLibrary("the feature", extra)) == f"the feature needs {names}: {command}"
