"""Usage mistakes: one line each, exit 2, no traceback (in this process, and plain
``rtupoll`` through the real console script)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from cli_runner import Ran
from cli_runner import rtupoll as run
from forked_cli import rtupoll_run


def rtupoll(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RTUPOLL_")}
    return rtupoll_run([sys.executable, "-m", "rtupoll", *args], capture_output=True,
                          text=True, timeout=60, env=env)


def in_process(*args: str) -> Ran:
    """The same command in this process (tests/cli_runner.py)."""
    return run(*args, env={k: None for k in os.environ if k.startswith("RTUPOLL_")})


@pytest.mark.parametrize(("args", "line"), [
    (["read", "huiwen-aq@3"],
     "rtupoll: which port? give --port PORT (e.g. -p /dev/ttyUSB0, or tcp://HOST:PORT for a "
     "gateway), or set $RTUPOLL_PORT"),
    (["reed"], "rtupoll: no command 'reed' (did you mean 'read'?) (see 'rtupoll --help')"),
    (["poll", "--simulate", "--bogus"],
     "rtupoll: No such option '--bogus'. Did you mean '--baud'? (see 'rtupoll poll --help')"),
    (["read", "-p", "/dev/null", "huiwen-aq@300"],
     "rtupoll: address 300 is outside 0..255 in 'huiwen-aq@300'"),
])
def test_usage_mistakes_are_one_line_and_exit_2(args: list[str], line: str) -> None:
    proc = in_process(*args)
    assert proc.returncode == 2
    assert len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.strip() == line
    assert "Traceback" not in proc.stderr


def test_plain_rtupoll_prints_the_help() -> None:
    proc = rtupoll()
    assert proc.returncode == 0
    assert proc.stdout.startswith("Usage: rtupoll [OPTIONS] COMMAND [ARGS]...")
    assert "Exit codes:" in proc.stdout


def test_a_file_that_is_not_a_serial_port_says_so() -> None:
    proc = in_process("read", "-p", "/dev/null", "huiwen-aq@1", "co2")
    assert proc.returncode == 3
    assert proc.stderr == "rtupoll: /dev/null is not a serial port\n"


@pytest.mark.parametrize("argv0, ours", [
    ("/usr/lib/python3/site-packages/pytest/__main__.py", False),  # python -m pytest
    ("/usr/local/bin/someapp", False),
    ("/home/u/.venv/bin/rtupoll", True),  # the console script
    (os.path.join("src", "rtupoll", "__main__.py"), True),  # python -m rtupoll
])
def test_the_early_signal_handler_is_only_installed_in_rtupolls_own_process(
        argv0: str, ours: bool) -> None:
    """Importing rtupoll's CLI in another program (pytest run as ``python -m pytest``)
    leaves that program's Ctrl-C alone; rtupoll's own process gets the one-line exit."""
    probe = ("import signal, sys; sys.argv[0] = sys.argv[1]; "
             "before = signal.getsignal(signal.SIGINT); import rtupoll.cli; "
             "print(signal.getsignal(signal.SIGINT) is before)")
    out = subprocess.run([sys.executable, "-c", probe, argv0], capture_output=True,
                         text=True, timeout=60, check=True).stdout.strip()
    assert out == str(not ours)
