"""The real CLI at real terminal sizes (issue 28, items 1 and 2): captured from tmux (a
terminal of exactly 80x24, or wider) and from pipes, not from a renderer in-process.

At 80x24 health and line trouble come first, then as many readings as fit, with a line
saying how many more there are; no column is silently dropped; no border touches text.
Piped, ``poll`` writes records as they come and says so in one stderr line.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from cli_runner import rtupoll
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus

RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))
Sim = Callable[..., SimulatedBus]
pytestmark = pytest.mark.skipif(shutil.which("tmux") is None, reason="needs tmux")


_SESSIONS = itertools.count()  # a tmux server of its own for each terminal, even in a row


@contextmanager
def terminal(width: int, height: int, command: list[str]) -> Iterator[Callable[[], list[str]]]:
    """``command`` in a tmux pane of ``width`` x ``height``; yields a screen grabber."""
    sock = f"rtupoll-test-{os.getpid()}-{next(_SESSIONS)}-{width}x{height}"  # one a call
    tmux = ["tmux", "-L", sock]
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    env["TERM"] = "xterm-256color"  # the size is the terminal's, as for a person
    subprocess.run([*tmux, "-f", "/dev/null", "new-session", "-d", "-x", str(width), "-y",
                    str(height), " ".join(command) + "; sleep 60"], check=True, env=env)
    subprocess.run([*tmux, "set-option", "-g", "window-size", "manual"], check=True)
    subprocess.run([*tmux, "resize-window", "-x", str(width), "-y", str(height)], check=True)

    def screen() -> list[str]:
        out = subprocess.run([*tmux, "capture-pane", "-p"], capture_output=True, text=True,
                             check=True).stdout
        return out.rstrip("\n").split("\n")
    pane = int(subprocess.run([*tmux, "list-panes", "-F", "#{pane_pid}"], capture_output=True,
                              text=True, check=True).stdout.split()[0])
    try:
        yield screen
    finally:
        # the pane is a session of its own: end the command in it (SIGHUP from tmux would
        # only make poll reload), then the server
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pane, signal.SIGTERM)
        subprocess.run([*tmux, "kill-server"], check=False, capture_output=True)


def wait_for(screen: Callable[[], list[str]], done: Callable[[list[str]], bool]) -> list[str]:
    deadline = time.monotonic() + 60  # a guard against a hang, not a timing claim
    while True:
        lines = screen()
        if done(lines) or time.monotonic() > deadline:
            return lines
        time.sleep(0.1)  # (a capture is one short tmux command)


def test_poll_at_80x24_shows_every_devices_health_and_says_what_is_cut() -> None:
    cmd = [RTUPOLL, "poll", "--simulate", "epever-tracer@2", "eastron-sdm630@1"]
    with terminal(80, 24, cmd) as screen:
        lines = wait_for(screen, lambda s: sum(" online " in x for x in s) >= 2
                         and any("scans" in x for x in s))
    text = "\n".join(lines)
    assert len(lines) <= 24 and all(len(x) <= 80 for x in lines), text
    assert "2/2 online" in lines[0]
    bus = next(i for i, x in enumerate(lines) if x.startswith("bus simulated"))
    health = {x.split()[0]: x.split() for x in lines[bus + 2:] if x.strip()}
    assert health["eastron-sdm630@1"][1] == "online" and health["epever-tracer@2"][1] == "online"
    assert lines[bus + 1].split()[:4] == ["device", "state", "ok", "timeout"]
    assert re.search(r"^… \d+ more lines? of readings: a taller terminal shows them$", text,
                     re.M), text
    assert "..." not in text  # nothing cropped by the terminal: the view fitted itself
    assert "voltage_l1" in text  # readings as far as they fit


def test_poll_in_a_tall_wide_terminal_has_one_row_per_field_with_every_column() -> None:
    cmd = [RTUPOLL, "poll", "--simulate", "huiwen-aq@3", "net-irnet-pro@1"]
    with terminal(120, 40, cmd) as screen:
        lines = wait_for(screen, lambda s: sum(" online " in x for x in s) >= 2
                         and any(re.search(r" temperature .*\d │", x) for x in s))
    head = next((x for x in lines if x.startswith("device")), "\n".join(lines))
    assert [c.strip() for c in head.split("┃")][:7] == [
        "device", "field", "value", "unit", "severity", "status", "age"]
    temperature = next(x for x in lines if " temperature " in x and "net-irnet" in x)
    assert " °C " in temperature and " K " not in temperature  # kelvin shown in °C
    assert re.search(r"│\s+(1[89]|2\d)\.\d\d │ °C ", temperature), temperature  # a room


def test_sniff_at_80x24_shows_health_and_line_trouble_first(sim: Sim, tmp_path: Path) -> None:
    tap = tmp_path / "tap"
    bus = sim("huiwen-aq@3", "radar-level@2", "net-irnet-pro@1", tap=str(tap))
    poller = rtupoll_popen([RTUPOLL, "poll", "-p", bus.port, "-b", "9600", "--format",
                               "json", "huiwen-aq@3", "radar-level@2", "net-irnet-pro@1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        cmd = [RTUPOLL, "sniff", "-p", str(tap), "-b", "9600", "huiwen-aq@3",
               "radar-level@2", "net-irnet-pro@1"]
        with terminal(80, 24, cmd) as screen:
            lines = wait_for(screen, lambda s: any("transactions; stray bytes" in x
                                                   for x in s)
                             and sum("@" in x and " │ " in x for x in s) >= 6)
    finally:
        poller.send_signal(signal.SIGINT)
        poller.wait(timeout=20)
    text = "\n".join(lines)
    assert len(lines) <= 24, text
    health = [x for x in lines if re.match(r"^\s+\d+ │ \S+@\d", x)]
    assert len(health) == 3, text  # every unit's row
    trouble = next(i for i, x in enumerate(lines) if "stray bytes" in x)
    assert "broken frames" in text and "replies to no request" in text
    assert trouble < next(i for i, x in enumerate(lines) if x.startswith("device"))
    assert not re.search(r"┃\S|\S┃|│\S(?<!─)", text.replace("┃━", "").replace("━┃", "")), text


def test_a_piped_poll_once_at_80_columns_keeps_every_column_and_one_header_row() -> None:
    run = rtupoll("poll", "--simulate", "epever-tracer@2", "eastron-sdm630@1", "--once",
                  env={"COLUMNS": "80"})  # piped: in this process (tests/cli_runner.py)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert all(len(x) <= 80 for x in lines)
    head = [i for i, x in enumerate(lines) if "┃" in x]
    assert len(head) == 1, run.stdout  # one header row, not an empty one above it
    cols = [c.strip() for c in lines[head[0]].split("┃")]
    assert "status" in cols and "value" in cols and "unit" in cols, cols
    assert not any(x.strip().strip("┃ ") == "" and "┃" in x for x in lines)
    # the footer's numbers are whole: no "271 …"
    assert "…" not in "\n".join(lines[lines.index(next(x for x in lines
                                                        if x.startswith("bus "))):])


def test_a_piped_poll_prints_records_as_they_come_and_says_so() -> None:
    proc = rtupoll_popen([RTUPOLL, "poll", "--simulate", "huiwen-aq@3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        assert ready, "nothing on stdout while it polls"
        first = json.loads(proc.stdout.readline())
        assert first["device"] == "huiwen-aq@3" and first["status"] == "ok"
        assert proc.poll() is None  # still polling: records came before the end
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0
    said = [x for x in err.splitlines() if x.strip()]
    assert said[0] == ("rtupoll: stdout is not a terminal: readings go out as JSON lines as "
                       "they come (--format json; or csv, influx; --once for one table)")


def test_profiles_list_and_search_keep_one_line_a_profile_at_80_columns() -> None:
    from rtupoll.config.library import load_library

    ids = set(load_library().profiles)
    for command, last in (([RTUPOLL, "profiles", "list"], None),
                          ([RTUPOLL, "profiles", "search", "battery_soc"], "renogy-rover")):
        with terminal(80, 24, [*command, ";", "echo", "__shown__"]) as screen:
            lines = wait_for(screen, lambda s: "__shown__" in s)  # all of it, not a part
        lines = lines[:lines.index("__shown__")]
        text = "\n".join(lines)
        assert all(len(x) <= 80 for x in lines), text
        rows = [x for x in lines if x[:3] == "   " and x.split()[:1] and x.split()[0] in ids]
        assert len(rows) >= (2 if last else 10), text  # a screenful of profiles
        wrapped = [x for x in lines[3:] if x.startswith("    ") and x.strip()]  # (the title)
        assert not wrapped, text  # no line continues a profile's row
        for row in rows:  # each one line: its id, its device cut short, its level whole
            assert re.search(r"(vendor doc|2 impls|UNVERIFIED)", row), text
            if last:
                assert row.rstrip().endswith("field battery_soc"), text
