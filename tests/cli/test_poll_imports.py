"""``rtupoll poll`` writing records imports no rich (the live table's library): less
memory for a long-running poller (benchmarks/poll_rss.py). Whether the table is drawn
beside ``-o FILE`` is still rich's own decision whenever it could be yes."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from rtupoll.sim.runner import SimulatedBus


def poll_once(port: str, out: Path, **given: str) -> tuple[set[str], str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("FORCE_COLOR", "TTY_COMPATIBLE", "FORCE_TERMINAL")}
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "rtupoll", "poll", "--port", port,
         "--once", "--format", "json", "-o", str(out), "huiwen-aq@1"],
        capture_output=True, text=True, timeout=60, env={**env, **given})
    assert proc.returncode == 0, proc.stderr[-2000:]
    modules = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines()
               if line.startswith("import time:") and line.count("|") == 2}
    return modules, proc.stdout


def test_records_to_a_file_import_no_rich(sim: Callable[..., SimulatedBus],
                                          tmp_path: Path) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    modules, stdout = poll_once(bus.port, tmp_path / "r.jsonl")
    assert '"device":"huiwen-aq@1"' in (tmp_path / "r.jsonl").read_text()
    assert "rtupoll.jobs.scheduler" in modules  # it polled
    assert not {m for m in modules if m == "rich" or m.startswith(("rich.", "rtupoll.ui.live"))}
    assert stdout == ""


def test_the_table_beside_the_file_when_rich_says_terminal(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    # rich 14 and later read TTY_COMPATIBLE; the lowest allowed rich (13) reads FORCE_COLOR
    modules, stdout = poll_once(bus.port, tmp_path / "r.jsonl", TTY_COMPATIBLE="1",
                                FORCE_COLOR="1")
    assert "rich.console" in modules
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", stdout)  # colours and cursor moves
    assert "1/1 online" in text and "co2" in text
