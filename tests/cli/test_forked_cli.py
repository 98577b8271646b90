"""A command forked from the fork server (tests/forked_cli.py) is what a fresh one is:
the same signal state, the same answer to Ctrl-C, SIGTERM and SIGHUP, to a reader that
leaves early and on a terminal; and a signal sent at any moment, right after the start
too, is never lost. Each case runs both (``subprocess.Popen`` and ``rtupoll_popen``) and
compares them. ``RTUPOLL_FORK_STRESS=N`` (default 8) sets how many forked commands the
last test stops at random moments (``RTUPOLL_FORK_STRESS=400``: the long run)."""

from __future__ import annotations

import contextlib
import json
import os
import pty
import random
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import forked_cli
import pytest
from forked_cli import RTUPOLL, rtupoll_popen

from rtupoll.sim.runner import SimulatedBus

# (with RTUPOLL_TEST_FRESH=1 nothing is forked: there is nothing to compare)
pytestmark = pytest.mark.skipif(
    not hasattr(os, "pidfd_open") or os.environ.get("RTUPOLL_TEST_FRESH") == "1",
    reason="no fork server here, or RTUPOLL_TEST_FRESH=1")

Popen = Callable[..., "subprocess.Popen[Any]"]


def fresh(args: list[str], **kw: Any) -> subprocess.Popen[Any]:
    """A new interpreter, in a session of its own as the forked one is."""
    return subprocess.Popen(args, start_new_session=True, **kw)


BOTH = pytest.mark.parametrize("popen", [fresh, rtupoll_popen], ids=["fresh", "forked"])
GUARD = 60  # seconds: a guard against a hang, not a timing claim


# the signals a program can set: not the two the C library keeps for itself (glibc's 32
# and 33), whose state follows the parent's threads, not the program: glibc catches 33
# once a process starts a thread, and an exec sets what was caught to the default; so
# under a parent that ignores both, a command started by a test (threads) gets 33 as the
# default and one forked from the single-threaded server keeps it ignored
SETTABLE = sum(1 << (s - 1) for s in signal.valid_signals())


def status(pid: int) -> dict[str, int]:
    """The signal lines of /proc/PID/status: blocked, ignored, caught (bit masks of the
    signals a program can set)."""
    lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    return {k: int(v, 16) & SETTABLE for k, _, v in (line.partition(":") for line in lines)
            if k in ("SigBlk", "SigIgn", "SigCgt")}


def reading(pid: int) -> None:
    """Wait until ``pid`` is blocked reading a pipe (its stdin)."""
    deadline = time.monotonic() + GUARD
    while "pipe" not in Path(f"/proc/{pid}/wchan").read_text():
        assert time.monotonic() < deadline, "the command never waited for its input"
        time.sleep(0.02)


@contextlib.contextmanager
def ignoring(sig: signal.Signals | None) -> Iterator[None]:
    """This process ignores ``sig`` meanwhile (as under ``nohup``), which an exec keeps."""
    if sig is None:
        yield
        return
    was = signal.signal(sig, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(sig, was)


@pytest.mark.parametrize("ignored", [None, signal.SIGHUP, signal.SIGINT],
                         ids=["nothing-ignored", "sighup-ignored", "sigint-ignored"])
def test_a_forked_command_has_a_fresh_ones_signal_state(ignored: signal.Signals | None
                                                        ) -> None:
    """The kernel's view of both, waiting for their input: the same signals blocked,
    ignored and caught (what this process ignores, an exec keeps: so does the fork)."""
    seen = []
    with ignoring(ignored):
        for popen in (fresh, rtupoll_popen):
            proc = popen([RTUPOLL, "decode", "-"], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            try:
                reading(proc.pid)
                seen.append(status(proc.pid))
            finally:
                proc.communicate(b"01 04 00 06 00 02 91 CA\n", timeout=GUARD)
            assert proc.returncode == 0
    assert seen[0] == seen[1]
    caught = seen[0]["SigCgt"]
    assert caught >> (signal.SIGINT - 1) & 1 and caught >> (signal.SIGTERM - 1) & 1


def simulate(popen: Popen, sig: signal.Signals) -> tuple[int, str, str]:
    """``rtupoll simulate`` stopped by ``sig`` once it has said it runs."""
    proc = popen([RTUPOLL, "simulate", "huiwen-aq@3", "--seed", "1"], stdin=subprocess.DEVNULL,
                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    out = ""
    while "Ctrl-C to stop." not in out:
        line = proc.stdout.readline()
        assert line, proc.communicate(timeout=GUARD)
        out += line
    os.killpg(proc.pid, sig)
    rest, err = proc.communicate(timeout=GUARD)
    return proc.returncode, re.sub(r"/dev/pts/\d+", "PTS", out + rest), err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_forked_command_that_runs_until_stopped_stops_as_a_fresh_one(sig: signal.Signals
                                                                       ) -> None:
    forked = simulate(rtupoll_popen, sig)
    assert forked == simulate(fresh, sig)
    assert forked[0] == 0 and "stopped after" in forked[1]


def site(path: Path, port: str, name: str) -> Path:
    path.write_text(f"buses:\n  - port: {port}\n    baudrate: 9600\n    devices:\n"
                    f"      - {{name: {name}, profile: huiwen-aq, address: 3, interval: 0.1,"
                    " fields: [co2]}\n")
    return path


@BOTH
def test_a_forked_poll_reloads_on_sighup_as_a_fresh_one(
        popen: Popen, sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    """SIGHUP: the site file is read again (the device's new name in the records), then
    SIGTERM ends it cleanly (exit 0, nothing on stderr)."""
    bus = sim("huiwen-aq@3")
    path = site(tmp_path / "site.yaml", bus.port, "before")
    proc = popen([sys.executable, "-m", "rtupoll", "poll", "-c", str(path), "--format", "json"],
                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    names = [json.loads(proc.stdout.readline())["device"]]
    site(path, bus.port, "after")
    proc.send_signal(signal.SIGHUP)
    while names[-1] != "after":
        line = proc.stdout.readline()
        assert line, proc.communicate(timeout=GUARD)
        names.append(json.loads(line)["device"])
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=GUARD)
    assert (proc.returncode, err) == (0, "")
    assert set(names) == {"before", "after"}


def reader_leaves(popen: Popen) -> tuple[int, str]:
    proc = popen([RTUPOLL, "poll", "--simulate", "huiwen-aq@3", "--format", "json",
                  "--interval", "0.05"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    assert json.loads(proc.stdout.readline())["device"]
    proc.stdout.close()  # the reader is done (``| head -1``): the next write is EPIPE
    err = proc.stderr.read().decode()
    return proc.wait(timeout=GUARD), err


def test_a_forked_command_whose_reader_leaves_ends_as_a_fresh_one() -> None:
    forked = reader_leaves(rtupoll_popen)
    assert forked == reader_leaves(fresh)
    assert "Traceback" not in forked[1]


def on_a_terminal(popen: Popen, args: list[str]) -> tuple[int, bytes]:
    main, child = pty.openpty()
    env = {**os.environ, "COLUMNS": "90", "LINES": "40", "TERM": "xterm-256color"}
    env.pop("NO_COLOR", None)
    proc = popen([RTUPOLL, *args], stdin=subprocess.DEVNULL, stdout=child, stderr=child,
                 env=env)
    os.close(child)
    out = b""
    with contextlib.suppress(OSError):  # EIO: the command is gone
        while data := os.read(main, 65536):
            out += data
    os.close(main)
    return proc.wait(timeout=GUARD), out


def test_a_forked_command_on_a_terminal_writes_what_a_fresh_one_writes() -> None:
    """Colours, width and line buffering follow the terminal, as at a fresh start."""
    forked = on_a_terminal(rtupoll_popen, ["profiles", "list"])
    assert forked == on_a_terminal(fresh, ["profiles", "list"])
    assert forked[0] == 0 and b"\x1b[" in forked[1]


COMMANDS = [
    [RTUPOLL, "simulate", "huiwen-aq@3"],
    [RTUPOLL, "simulate", "--tcp", "127.0.0.1:0", "huiwen-aq@3", "--seed", "1"],
    [sys.executable, "-m", "rtupoll", "poll", "--simulate", "huiwen-aq@3"],
    [RTUPOLL, "poll", "--simulate", "huiwen-aq@3", "--format", "json"],
    [RTUPOLL, "poll", "--simulate", "huiwen-aq@3", "--http", "127.0.0.1:0"],
]


def stop_at_random(rng: random.Random, failures: list[str]) -> None:
    """One forked command that runs until stopped, given SIGINT or SIGTERM at a random
    moment (often at once), on a terminal or pipes: it ends, stopped (0) or interrupted
    (130). (A signal in the first milliseconds of ``asyncio.run`` can add asyncio's
    "Exception ignored" lines to "rtupoll: interrupted", as in a fresh process.)"""
    args = rng.choice(COMMANDS)
    delay = rng.choice([0.0, 0.0, 0.001, 0.01, 0.05, rng.uniform(0, 1.5)])
    sig = rng.choice([signal.SIGINT, signal.SIGINT, signal.SIGTERM])
    main, child = pty.openpty() if rng.random() < 0.3 else (None, None)
    proc = rtupoll_popen(args, stdin=subprocess.DEVNULL,
                         stdout=child if child is not None else subprocess.DEVNULL,
                         stderr=child if child is not None else subprocess.PIPE)
    said = b""
    if main is not None and child is not None:
        os.close(child)

        def drain() -> None:
            nonlocal said
            with contextlib.suppress(OSError):
                while data := os.read(main, 65536):
                    said += data
        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
    time.sleep(delay)
    os.killpg(proc.pid, sig)
    try:
        proc.wait(timeout=GUARD)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        failures.append(f"{args[1:]} did not stop on {sig.name} sent after {delay:.3f} s")
    if main is not None:
        reader.join(timeout=GUARD)
        os.close(main)
    else:
        assert proc.stderr is not None
        said = proc.stderr.read()
        proc.stderr.close()
    if proc.returncode not in (0, 130):  # stopped, or interrupted before it ran
        failures.append(f"{args[1:]} {sig.name} after {delay:.3f} s: exit {proc.returncode}"
                        f" {said[-2000:].decode(errors='replace')}")


def test_forked_commands_stop_on_a_signal_at_any_moment() -> None:
    """Commands that run until stopped, four at a time from one server, each stopped at a
    random moment (right after the start too): none is left running, none fails."""
    runs = int(os.environ.get("RTUPOLL_FORK_STRESS", "8"))
    seed = random.randrange(1 << 32)
    failures: list[str] = []

    def worker(k: int) -> None:
        rng = random.Random(seed + k)
        for _ in range(k, runs, 4):
            stop_at_random(rng, failures)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures, f"seed {seed}: " + "\n".join(failures)


def test_a_ctrl_c_whose_keyboardinterrupt_python_drops_still_stops_the_command(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A Ctrl-C in the instant a weakref callback (or a ``__del__``) runs, before the
    command has set its own handler: Python prints "Exception ignored" and drops the
    KeyboardInterrupt. The command still learns of it (``rtupoll.cli.stop_event`` and
    ``noted_signals`` start set) and
    stops, instead of running until a second Ctrl-C (the stress test above met it)."""
    import weakref

    from cli_runner import rtupoll

    import rtupoll.sim.runner as runner

    real = runner.simulated_lines
    dropped: list[bool] = []

    def lines_after_a_dropped_ctrl_c(*args: Any, **kw: Any) -> Any:
        class Thing:
            pass

        def callback(_: object) -> None:
            signal.raise_signal(signal.SIGINT)
            dropped.append(True)  # (a call: Python runs the handler here, in the callback)

        thing = Thing()
        ref = weakref.ref(thing, callback)
        del thing  # the callback runs now; its KeyboardInterrupt is "ignored"
        assert ref() is None
        return real(*args, **kw)

    monkeypatch.setattr(runner, "simulated_lines", lines_after_a_dropped_ctrl_c)
    ignored: list[type[BaseException] | None] = []  # what Python said "Exception ignored" of
    monkeypatch.setattr(sys, "unraisablehook", lambda u: ignored.append(u.exc_type))
    stopped_by_the_guard = threading.Event()

    def against_a_hang() -> None:
        stopped_by_the_guard.set()
        signal.raise_signal(signal.SIGTERM)

    guard = threading.Timer(GUARD, against_a_hang)
    guard.start()
    try:
        ran = rtupoll("simulate", "huiwen-aq@3")
    finally:
        guard.cancel()
    assert not stopped_by_the_guard.is_set(), "it ran on after the Ctrl-C"
    assert dropped == [] and ignored == [KeyboardInterrupt]  # it was raised, and dropped
    assert ran.returncode == 0 and "stopped after 0 requests" in ran.stdout


# How a forked command ends (tests/forked_cli.py, ``exit_unshared``): its last atexit
# callback flushes, collects and exits without tearing down the modules the child
# shares with the server. Each case ends a fresh Python so, and again with Python's own
# exit; the two must show the same (status, stdout, stderr).
EXIT_SCRIPT = """
import atexit, sys
sys.path.insert(0, sys.argv[1])
import forked_cli
if sys.argv[2] == "unshared":
    atexit.register(forked_cli.exit_unshared)
atexit.register(print, "an atexit callback", file=sys.stderr)

class Noisy:
    def __del__(self):
        print("a finalizer", file=sys.stderr)

def command():
{case}

forked_cli.ending(command)
"""
EXIT_CASES = {
    "status": "    print('out'); sys.exit(3)",
    "message": "    sys.exit('rtupoll: a message')",
    "error": "    raise ValueError('an error')",
    "ctrl-c": "    raise KeyboardInterrupt",
    "buffered": "    sys.stdout.write('x' * 100)",  # (fully buffered: written at the exit)
    "cycle": "    a = Noisy(); a.me = a; del a",  # garbage with a finalizer, collected at exit
    "flush-fails": "    sys.stdout.write('x' * 100); sys.exit(0)",  # (stdout's reader gone)
}


def ended(case: str, how: str) -> tuple[int, str, str]:
    """(status, stdout, stderr) of ``EXIT_CASES[case]`` ended by ``exit_unshared``
    (``how="unshared"``) or by Python alone (``how="python"``)."""
    return ended_with(EXIT_CASES[case], how, gone=case == "flush-fails")


def ended_with(body: str, how: str, *, gone: bool = False) -> tuple[int, str, str]:
    script = EXIT_SCRIPT.format(case=body)
    read, write = os.pipe()
    if gone:
        os.close(read)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # (buffered)
    proc = subprocess.Popen([sys.executable, "-c", script, str(Path(forked_cli.__file__).parent),
                             how], stdout=write, stderr=subprocess.PIPE, text=True, env=env)
    os.close(write)
    out = ""
    if not gone:
        with os.fdopen(read) as reading:
            out = reading.read()
    _, err = proc.communicate(timeout=GUARD)
    return proc.returncode, out, err


@pytest.mark.parametrize("case", sorted(EXIT_CASES))
def test_a_forked_commands_exit_shows_what_pythons_exit_shows(case: str) -> None:
    unshared = ended(case, "unshared")
    assert unshared == ended(case, "python")
    assert "an atexit callback" in unshared[2]
    want = {"status": 3, "message": 1, "error": 1, "ctrl-c": -signal.SIGINT, "buffered": 0,
            "cycle": 0, "flush-fails": 120}
    assert unshared[0] == want[case]


def test_what_a_forked_commands_exit_does_not_do_is_tear_down_the_modules() -> None:
    """Its one difference: a finalizer that only the modules' teardown runs (of an object a
    module still holds at the exit) does not run."""
    held = "    sys.modules['forked_cli'].held = Noisy()"
    python, unshared = ended_with(held, "python"), ended_with(held, "unshared")
    assert python[2].endswith("a finalizer\n") and "a finalizer" not in unshared[2]
    assert python[:2] == unshared[:2] == (0, "")
