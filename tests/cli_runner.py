"""The real ``rtupoll`` command, run in the test's own process: ``rtupoll(*args)``.

Most CLI tests are about what a command does and prints, not about a new process: this
runs the console script's own entry point (``rtupoll.cli.main``: the usage errors, the
error-to-exit-code mapping, the stdout guard, the signal handlers it sets while a command
runs) with the arguments, standard input and environment given, and returns what a
subprocess would: ``returncode``, ``stdout``, ``stderr`` (plus ``cpu``, the CPU seconds the
command took). It costs the command's own work, not Python's and rtupoll's start-up (a
subprocess: 0.15-0.4 CPU-s). Devices are the simulator's, on real ptys or TCP.

What a process has and a run must not leave behind is saved before and put back after:
the environment, the working directory, the standard streams, the handlers of every
signal, the ``rtupoll`` loggers' handlers and levels (and the root logger's), warning
filters, the asyncio event loop policy. What a new process would not have yet is not
there while a command runs: logging's handlers (pytest's capture among them), the
simulator's profile-by-id cache (its key has the environment's RTUPOLL_PROFILES, not the
files' contents) and the unverified profiles already warned about (once a process).
tests/cli/test_cli_runner.py proves two runs do not leak into each other.

Standard input, output and error are not terminals (as in a subprocess with pipes).
What needs a process stays a process (``forked_cli.rtupoll_popen``/``rtupoll_run``:
forked from a server that imported rtupoll once; ``subprocess`` for a fresh one): a
signal from outside, a terminal, a closed or full descriptor, the process's own exit;
imports at start-up and an early Ctrl-C need a fresh one. Tests keep at least one of
those per command and per fault family.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import time
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from click.testing import CliRunner

# imported once, here: under ``python -m pytest`` importing it sets the early-signal
# handler of the console script (rtupoll/cli/__init__.py), which is then the process's
from rtupoll.cli import main

__all__ = ["RTUPOLL", "Ran", "isolated", "rtupoll"]

RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))  # the console script
# every signal a command may handle (SIGKILL and SIGSTOP cannot be)
_SIGNALS = [s for s in signal.valid_signals() if s not in (signal.SIGKILL, signal.SIGSTOP)]


@dataclass(frozen=True)
class Ran:
    """What ``rtupoll`` did: as ``subprocess.CompletedProcess`` names it."""

    args: tuple[str, ...]
    returncode: int
    stdout: str
    stderr: str
    cpu: float  # CPU seconds of the test's thread while the command ran


def _loggers() -> dict[str, logging.Logger]:
    """The root logger and every ``rtupoll`` logger that exists now."""
    named = logging.root.manager.loggerDict
    return {"": logging.getLogger(), **{name: log for name, log in named.items()
                                        if isinstance(log, logging.Logger)
                                        and name.split(".")[0] == "rtupoll"}}


@contextlib.contextmanager
def isolated(cwd: str | Path | None = None) -> Iterator[None]:
    """Everything process-wide a command may change, put back afterwards; and what a
    process remembers from its start (the profile-by-id cache, the unverified profiles
    it already warned about), empty while the command runs, as in a new process."""
    from rtupoll.config import library
    from rtupoll.sim import scenario

    environ = dict(os.environ)
    here = os.getcwd()
    streams = sys.stdin, sys.stdout, sys.stderr
    handlers = {s: signal.getsignal(s) for s in _SIGNALS}
    loggers = {name: (list(log.handlers), log.level, log.propagate, log.disabled)
               for name, log in _loggers().items()}
    disabled = logging.root.manager.disable
    policy = asyncio.get_event_loop_policy()
    remembered = [(memory, memory.copy()) for memory in (scenario._CACHE, library._WARNED)]
    for memory, _ in remembered:
        memory.clear()
    # logging as a new process has it: no handlers (a warning goes to stderr through
    # logging's last resort, not to pytest's capture), the root at WARNING
    for log in _loggers().values():
        log.handlers[:] = []
        log.setLevel(logging.NOTSET)
        log.propagate, log.disabled = True, False
    logging.getLogger().setLevel(logging.WARNING)
    logging.disable(logging.NOTSET)
    try:
        with warnings.catch_warnings():
            if cwd is not None:
                os.chdir(cwd)
            yield
    finally:
        os.chdir(here)
        os.environ.clear()
        os.environ.update(environ)
        sys.stdin, sys.stdout, sys.stderr = streams
        for s, handler in handlers.items():
            if handler is not None and signal.getsignal(s) is not handler:
                signal.signal(s, handler)
        for name, log in _loggers().items():
            hs, level, propagate, off = loggers.get(name, ([], logging.NOTSET, True, False))
            log.handlers[:] = hs
            log.setLevel(level)
            log.propagate, log.disabled = propagate, off
        logging.disable(disabled)
        asyncio.set_event_loop_policy(policy)
        for memory, was in remembered:
            memory.clear()
            memory.update(was)


def rtupoll(*args: str, input: str | bytes | None = None,
            env: Mapping[str, str | None] | None = None,
            cwd: str | Path | None = None) -> Ran:
    """Run ``rtupoll ARGS`` in this process. ``env``: variables to set (None: unset) on
    top of this process's environment; ``cwd``: the working directory."""
    runner = CliRunner()
    code: Any = 0
    with isolated(cwd), runner.isolation(input=input, env=env) as (out, err, _):
        start = time.thread_time()
        try:
            main(list(args))
        except SystemExit as exc:
            code = exc.code
        finally:
            cpu = time.thread_time() - start
            sys.stdout.flush()
            sys.stderr.flush()
        stdout, stderr = out.getvalue(), err.getvalue()
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): a message and 1, as Python does
        stderr += f"{code}\n".encode()
        code = 1
    return Ran(tuple(args), code, stdout.decode("utf-8", "replace"),
               stderr.decode("utf-8", "replace"), cpu)

