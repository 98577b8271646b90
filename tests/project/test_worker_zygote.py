"""A pytest-xdist worker forked from the zygote (tests/worker_zygote.py) starts as the
fresh ``PYTHON -u -c CODE`` that execnet would have started: the same view of its
arguments, path, directory, environment, signals and stdio, the same exit status, and
the same pipes, which close when it ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import worker_zygote

# what a worker's Python sees of itself (the code execnet's -c would run instead)
STATE = r"""
import json, os, signal, sys
def stream(s):
    return [s.fileno(), s.isatty(), s.line_buffering, s.write_through, s.encoding, s.errors]
line = sys.stdin.readline()
print(json.dumps({
    "argv": sys.argv, "path0": sys.path[0], "cwd": os.getcwd(), "name": __name__,
    "env": os.environ.get("RTUPOLL_ZYGOTE_PROBE"), "bytecode": sys.dont_write_bytecode,
    "signals": {s.name: str(signal.getsignal(s)) for s in signal.Signals
                if s not in (signal.SIGKILL, signal.SIGSTOP)},
    "stdin": line, "stdout": stream(sys.stdout), "stderr": stream(sys.stderr),
    "modules": "rtupoll.cli" in sys.modules, "collected": "test_worker_zygote" in sys.modules}))
sys.stdout.write("unbuffered")  # (no newline, no flush: seen only if written through)
sys.exit(int(line.split()[-1]))
"""


@pytest.fixture(scope="module")
def zygote() -> Iterator[str]:
    """The socket of a zygote that has collected this file: the run's, whose workers run
    these tests (pytest-xdist), else one started here as a run's is, with this file as
    its pytest arguments."""
    if not worker_zygote.available():
        pytest.skip("no zygote here (no pidfd, or RTUPOLL_TEST_FRESH=1): workers start fresh")
    if os.environ.get(worker_zygote.ENV):
        yield os.environ[worker_zygote.ENV]
        return
    server = worker_zygote.Listening(worker_zygote.__file__, "RTUPOLL_TEST_ZYGOTE_PROBE_SOCKET",
                                     "-q", __file__)
    try:
        yield os.environ["RTUPOLL_TEST_ZYGOTE_PROBE_SOCKET"]
    finally:
        server.close()


def start(zygote: str | None, where: Path, *flags: str) -> tuple[int, str, str]:
    """A worker's Python started as execnet starts it (``spec``'s words, then
    ``-u [-B] -c CODE``), through the zygote on that socket or fresh; its status, stdout
    and stderr."""
    env = {**os.environ, "RTUPOLL_ZYGOTE_PROBE": "here"}
    python = [sys.executable, "-I", "-S", worker_zygote.__file__] if zygote else [sys.executable]
    env.pop(worker_zygote.ENV, None)
    if zygote:
        env[worker_zygote.ENV] = zygote
    proc = subprocess.run([*python, "-u", *flags, "-c", STATE], input="exit with 3\n",
                          capture_output=True, text=True, cwd=where, env=env, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


@pytest.mark.parametrize("flags", [(), ("-B",)], ids=["bytecode", "no-bytecode"])
def test_a_forked_worker_starts_as_a_fresh_python(zygote: str, tmp_path: Path,
                                                  flags: tuple[str, ...]) -> None:
    fresh = start(None, tmp_path, *flags)
    forked = start(zygote, tmp_path, *flags)
    assert fresh[0] == 3 and fresh[1].endswith("unbuffered"), fresh
    state = {k: v for k, v in json.loads(fresh[1].splitlines()[0]).items()
             if k not in ("modules", "collected")}
    assert state["stdin"] == "exit with 3\n" and state["cwd"] == str(tmp_path)
    assert forked[0] == fresh[0] and forked[2] == fresh[2] == ""
    assert forked[1].splitlines()[1:] == fresh[1].splitlines()[1:]
    seen = json.loads(forked[1].splitlines()[0])
    assert seen.pop("modules") is True  # (what the zygote imported is there already,
    assert seen.pop("collected") is True  # the test files it collected too)
    assert seen == state


def test_a_worker_killed_by_a_signal_ends_its_client_so(zygote: str, tmp_path: Path) -> None:
    """execnet sees the worker's Python end as the worker ended: by the same signal."""
    env = {**os.environ, worker_zygote.ENV: zygote}
    code = "import os, signal, sys; sys.stdin.readline(); os.kill(os.getpid(), signal.SIGTERM)"
    proc = subprocess.run([sys.executable, "-I", "-S", worker_zygote.__file__, "-u", "-c", code],
                          input="go\n", capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == -signal.SIGTERM, proc


def test_without_a_zygote_the_client_is_a_fresh_python(tmp_path: Path) -> None:
    """No socket (the zygote gone, or never started): the client execs the worker's
    Python itself, and the run goes on."""
    env = {**os.environ, worker_zygote.ENV: str(tmp_path / "no-such-socket")}
    proc = subprocess.run([sys.executable, "-I", "-S", worker_zygote.__file__, "-u", "-c",
                           "import sys; print(sys.argv, 'rtupoll.cli' in sys.modules)"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert (proc.returncode, proc.stdout) == (0, "['-c'] False\n"), proc


def test_a_held_run_goes_on_once_the_file_is_there(tmp_path: Path) -> None:
    gate = tmp_path / "parallel-run-ended"
    result: list[bool] = []
    held = threading.Thread(
        target=lambda: result.append(worker_zygote.hold(str(gate), os.getpid())))
    held.start()
    time.sleep(0.2)
    assert held.is_alive() and not result  # no file, no end
    gate.touch()
    held.join(timeout=60)  # (a hang guard)
    assert result == [True]


def test_a_held_run_whose_owner_ends_does_not_wait_on(tmp_path: Path) -> None:
    """scripts/test stopped before it made the file: the held run ends, not waits on
    (also when its owner has ended before the hold began, and before it is reaped)."""
    code = (f"import os, sys; sys.path.insert(0, {str(Path(worker_zygote.__file__).parent)!r})\n"
            "import worker_zygote\n"
            "owner = os.getpid()\n"
            "if os.fork():\n"
            "    os._exit(0)  # the owner ends at once\n"
            f"print(worker_zygote.hold({str(tmp_path / 'never')!r}, owner), flush=True)\n")
    # the held child keeps stdout open: it is read to the end once the child has ended
    # (and only then is the owner reaped)
    proc = subprocess.run([sys.executable, "-I", "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.stdout == "False\n", proc.stderr
