"""Ctrl-C where the event loop takes no signal handlers (Windows's ``ProactorEventLoop``
raises NotImplementedError from ``add_signal_handler``): ``poll`` ends as it does on
Linux, with the same exit code and output, instead of "interrupted" (exit 130). Here
the loop is made to refuse as Windows's does (the one thing made up), in a fresh process
given a real SIGINT; the Windows group runs it on Windows."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

GUARD = 60  # seconds: against a hang, not a timing claim

REFUSING = """\
import asyncio, asyncio.unix_events, sys
def refuse(self, *args, **kwargs):
    raise NotImplementedError  # as Windows's ProactorEventLoop
asyncio.unix_events._UnixSelectorEventLoop.add_signal_handler = refuse
sys.argv[0] = "rtupoll"
from rtupoll.cli import main
main()
"""


def stopped(tmp_path: Path, *, refusing: bool) -> tuple[int, str, int]:
    """``poll --simulate`` until its first record, then Ctrl-C: exit code, stderr, and
    how many records it wrote."""
    script = tmp_path / "refusing.py"
    script.write_text(REFUSING)
    head = [sys.executable, str(script)] if refusing else [sys.executable, "-m", "rtupoll"]
    proc = subprocess.Popen([*head, "poll", "--simulate", "huiwen-aq@3", "--format", "json",
                             "--interval", "0.05"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    assert json.loads(first)["device"] == "huiwen-aq@3", proc.communicate(timeout=GUARD)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=GUARD)
    return proc.returncode, err, len((first + out).splitlines())


@pytest.mark.skipif(sys.platform == "win32", reason="the loop is made to refuse as Windows's")
def test_ctrl_c_ends_poll_as_where_the_loop_takes_handlers(tmp_path: Path) -> None:
    code, err, records = stopped(tmp_path, refusing=True)
    assert (code, err) == stopped(tmp_path, refusing=False)[:2] == (0, "")
    assert records >= 1
