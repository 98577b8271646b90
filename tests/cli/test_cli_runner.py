"""The in-process runner (tests/cli_runner.py) is the real command, and one run leaves
nothing behind that the next run (or any other test in the process) would see."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cli_runner import _SIGNALS, RTUPOLL, rtupoll

from rtupoll.sim.runner import SimulatedBus


def process_state() -> dict[str, Any]:
    """What a run could change in the process."""
    return {
        "environ": dict(os.environ),
        "cwd": os.getcwd(),
        "streams": (sys.stdin, sys.stdout, sys.stderr),
        "signals": {s: signal.getsignal(s) for s in _SIGNALS},
        "loggers": {name: (list(log.handlers), log.level, log.propagate)
                    for name in ("", "rtupoll") for log in [logging.getLogger(name)]},
        "warnings": list(warnings.filters),
        "policy": asyncio.get_event_loop_policy(),
    }


def test_two_runs_do_not_leak_into_each_other(sim: Callable[..., SimulatedBus],
                                              tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    before = process_state()
    # the first run sets what a process would keep: a port in the environment, another
    # working directory, JSON logging (the rtupoll logger's handler and level), asyncio's
    # signal handlers while it polls, an output file named relative to the directory
    first = rtupoll("poll", "--once", "--format", "json", "--log-format", "json",
                    "-o", "out.json", "huiwen-aq@3",
                    env={"RTUPOLL_PORT": bus.port}, cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    records = [json.loads(line) for line in (tmp_path / "out.json").read_text().splitlines()]
    assert records and {r["status"] for r in records} == {"ok"}
    assert process_state() == before

    # the second sees none of it: no port from the environment, its output is its own,
    # and a warning shows once, in its own stderr
    second = rtupoll("read", "huiwen-aq@3", "co2")
    assert second.returncode == 2
    assert second.stdout == ""
    assert second.stderr == ("rtupoll: which port? give --port PORT (e.g. -p /dev/ttyUSB0, or "
                             "tcp://HOST:PORT for a gateway), or set $RTUPOLL_PORT\n")
    assert not (Path.cwd() / "out.json").exists()
    assert process_state() == before

    # and the logger the first run set up writes nowhere now
    logging.getLogger("rtupoll").error("after the runs")
    third = rtupoll("read", "-p", bus.port, "--format", "json", "huiwen-aq@3", "co2")
    assert third.returncode == 0, third.stderr
    assert third.stderr == "" and "after the runs" not in third.stdout
    assert json.loads(third.stdout)["field"] == "co2"


def test_in_process_and_as_a_process_the_command_says_the_same(
        sim: Callable[..., SimulatedBus]) -> None:
    """The runner is the console script's entry point: the same exit code, the same
    lines on stdout and stderr as the installed command (usage errors included)."""
    bus = sim("huiwen-aq@3", tick=None, sets=["huiwen-aq@3.co2=777"])
    env = {k: v for k, v in os.environ.items() if not k.startswith("RTUPOLL_")}
    for args in (["read", "-p", bus.port, "--format", "csv", "huiwen-aq@3", "co2",
                  "co2_level"],
                 ["reed"],
                 ["read", "-p", bus.port, "huiwen-aq@300"],
                 ["read", "-p", bus.port, "--timeout", "0.2", "--retries", "0",
                  "huiwen-aq@4", "co2"]):
        inside = rtupoll(*args, env={k: None for k in os.environ if k.startswith("RTUPOLL_")})
        outside = subprocess.run([RTUPOLL, *args], env=env, capture_output=True, text=True,
                                 timeout=60)
        assert (inside.returncode, inside.stderr) == (outside.returncode, outside.stderr), args
        # a record's time stamp is the only thing that may differ
        assert [line.split(",", 1)[-1] for line in inside.stdout.splitlines()] == \
            [line.split(",", 1)[-1] for line in outside.stdout.splitlines()], args


def test_each_run_warns_about_an_unverified_profile_as_a_new_process_would(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("md02@1", tick=None)
    args = ("read", "-p", bus.port, "--format", "json", "md02@1")
    for _ in range(2):
        ran = rtupoll(*args)
        assert ran.returncode == 0, ran.stderr
        assert "profile md02 is unverified" in ran.stderr
