"""Shared fixtures: simulated buses (that a test cannot leak) and a raw serial peer.

``sim(*devices, **options)`` starts a simulated bus (``rtupoll.sim.runner.simulated_bus``
arguments) and stops it after the test. Every test, whether or not it uses ``sim``, fails
if it leaves a simulated bus running: a leaked bus keeps a thread and a pty alive and
would answer the next test's requests.

``raw_port(path)`` opens a pty path (or ``tcp://HOST:PORT``) without any Modbus library,
so a test can send exact bytes and see exactly what came back.

``jitter`` is how late this machine wakes a sleeping thread now (seconds, the 99th
percentile of 200 one-millisecond sleeps): the allowance of a test in the ``timing``
group, the few that measure the real clock (scripts/test runs them after the parallel
run). Every other rule about time is proven in virtual time (tests/virtual.py), and a
reply that is to come is waited for ``ANSWERED`` (10 s), a wait it ends.

Hypothesis runs the ``short`` profile (few examples, the same ones every run) unless
``--hypothesis-profile=long`` or ``HYPOTHESIS_PROFILE=long`` asks for a long search.

The compiled profile cache (``rtupoll.config.compiled``) of a test run lives in a
directory of its own, set before any test module loads a profile and inherited by the
pytest-xdist workers and the CLI subprocesses tests start (the library compiled into it
once, before the workers start): no test reads or writes the user's ~/.cache.
"""

from __future__ import annotations

import atexit
import dataclasses
import gc
import itertools
import os
import select
import shutil
import socket
import tempfile
import termios
import time
import tty
from collections.abc import Awaitable, Callable, Collection, Generator, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest

# hypothesis runs the "hypothesis" entry points of every installed package when imported:
# trio's (installed for selenium) imports trio, a fifth of a second in every process
os.environ.setdefault("HYPOTHESIS_NO_PLUGINS", "1")
import forked_cli
import worker_zygote
from forked_cli import close_server
from hypothesis import settings

from rtupoll.config.library import load_library
from rtupoll.config.site import Site
from rtupoll.errors import DeviceTimeout
from rtupoll.sim.runner import SimulatedBus, running, simulated_bus

pytest_plugins = ("pytester", "cpu_report")

# one cache for the run: made by the process pytest was started as, inherited by the
# pytest-xdist workers it starts (each of which otherwise parsed every profile itself)
_CACHE = os.environ.get("RTUPOLL_TEST_CACHE", "")
if not os.path.isdir(_CACHE):
    _CACHE = os.environ["RTUPOLL_TEST_CACHE"] = tempfile.mkdtemp(prefix="rtupoll-test-cache-")
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["XDG_CACHE_HOME"] = _CACHE
# the ~285 rtupoll processes the suite starts reuse compiled bytecode, as scripts/test
# has them do, also when pytest is run directly where the environment turns caching
# off: compiling rtupoll's modules anew cost each start 40-80 ms of CPU (a third)
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# few examples, and the same ones every run, by default; a long, random search on demand.
# No deadline: an example's wall-clock time says how busy the machine is (a hang is
# caught by pytest-timeout, a blow-up by the CPU-time bounds of the tests themselves)
settings.register_profile("short", max_examples=25, derandomize=True, deadline=None)
settings.register_profile("long", max_examples=2000, derandomize=False, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "short"))


def pytest_configure(config: pytest.Config) -> None:
    """Before pytest-xdist starts its workers: they are to be forked from one process that
    has imported what they import (tests/worker_zygote.py), and the library's profiles
    are compiled into the run's cache once, so that no worker (each collects test files
    that load the library) nor the commands they start parses them again."""
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        if worker_zygote.available():
            try:
                _SERVERS.append(worker_zygote.Listening(
                    worker_zygote.__file__, worker_zygote.ENV, *config.invocation_params.args))
                # and one server for the rtupoll commands of every worker (tests/forked_cli.py)
                _SERVERS.append(worker_zygote.Listening(forked_cli.__file__, forked_cli.SHARED))
            except OSError as error:  # (e.g. a socket path too long): fresh workers, as before
                config.issue_config_time_warning(pytest.PytestConfigWarning(
                    f"workers start fresh: no zygote here ({error})"), stacklevel=2)
            else:
                config.option.tx = [worker_zygote.spec(tx) for tx in config.option.tx]
        load_library()


def pytest_unconfigure(config: pytest.Config) -> None:
    for server in _SERVERS:  # (told together, they end side by side)
        server.stop()
    for server in _SERVERS:
        server.close()
    _SERVERS.clear()


_SERVERS: list[worker_zygote.Listening] = []


def _timing_run(config: pytest.Config) -> bool:
    """A run of the ``timing`` group, or of part of it (``-m timing``, ``-m "timing and
    alone"``, ``-m "timing and not alone"``: scripts/test)."""
    markexpr: str = config.getoption("markexpr")
    return markexpr == "timing" or markexpr.startswith("timing and ")


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """The ``timing`` group (``-m timing``, scripts/test) imports only the test files
    that say ``mark.timing``: the group runs after the parallel run, so importing the
    other 100 files would be its wall time. Every other run checks that each test so
    marked says it in its file (``pytest_collection_modifyitems``). The ``windows``
    group (``-m windows``) likewise imports only the files that say ``mark.windows``."""
    said = ("mark.timing" if _timing_run(config) else
            "mark.windows" if config.getoption("markexpr") == "windows" else None)
    if (said and collection_path.suffix == ".py"
            and collection_path.name.startswith("test_")
            and said not in collection_path.read_text(encoding="utf-8")):
        return True
    return None


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config: pytest.Config,
                                  items: list[pytest.Item]) -> Generator[None, None, None]:
    """Every test marked ``timing`` says so in its file; then (once ``-m`` has deselected
    what does not run) the order for pytest-xdist's workers."""
    unsaid = sorted({str(item.path) for item in items if item.get_closest_marker("timing")
                     and "mark.timing" not in item.path.read_text(encoding="utf-8")})
    if unsaid:
        raise pytest.UsageError("tests marked timing in files that do not say 'mark.timing' "
                                "(-m timing would not run them): " + ", ".join(unsaid))
    yield
    if _timing_run(config):
        # pytest-xdist's ``--dist load`` hands the group round (fewer tests than two a
        # worker): the longest first, one to each worker, then the rest shortest first, so
        # that the worker with the longest gets the shortest. How long each took is the
        # last run's (the pytest cache); one not seen yet counts as long. Without a cache,
        # one test of each file, then the second of each, ...: a file's timing tests are
        # alike (two scans, two sniffs of mbpoll)
        files: dict[Path, list[pytest.Item]] = {}
        for item in items:
            files.setdefault(item.path, []).append(item)
        rounds = itertools.zip_longest(*files.values())
        items[:] = [item for round_ in rounds for item in round_ if item is not None]
        took = _took(config)
        if took:
            items.sort(key=lambda item: -took.get(item.nodeid, float("inf")))
            workers = getattr(config, "workerinput", {}).get("workercount", 1)
            items[workers:] = items[workers:][::-1]
        return
    # The browser tests first, so that pytest-xdist gives them to one worker: one chromium
    # for all of them (test_web_browser.py's ``one_chromium``), not one per worker that
    # gets one (each start is about 1 CPU-s and 2-4 s of wall). ``--dist worksteal`` hands
    # each worker a contiguous run of the collection and an idle worker steals from the
    # END of a busy one's run: tests at the very start stay with the first worker, in
    # order (``--dist loadgroup`` would keep an ``xdist_group`` together, but the suite
    # runs ``worksteal``; without xdist the order changes nothing).
    browser = [item for item in items if "one_chromium" in getattr(item, "fixturenames", ())]
    rest = [item for item in items if item not in browser]
    # The documents' examples (tests/project/test_docs_examples.py: 43 tests that mostly
    # wait on the commands they run, a minute in all) spread evenly through the rest:
    # last in the collection, they were the run's last tests, and its last 10 s kept a
    # core idle
    examples = [item for item in rest if item.path.name == "test_docs_examples.py"]
    others = [item for item in rest if item.path.name != "test_docs_examples.py"]
    if 0 < len(examples) <= len(others):
        every = len(others) / len(examples)
        at = {int(every * (k + 0.5)): example for k, example in enumerate(examples)}
        rest = [item for n, test in enumerate(others)
                for item in ([at[n]] if n in at else []) + [test]]
    items[:] = browser + rest


def pytest_collection_finish(session: pytest.Session) -> None:
    """What collecting made (the modules, the test items) lives to the end: out of the
    collector's sight, so that its full collections during the tests (hypothesis makes
    many objects) and pytest's at the end do not walk it each time.

    With ``RTUPOLL_TEST_AFTER="PID FILE"`` (scripts/test, its PID: the timing group,
    started while the parallel run still runs, and the ``alone`` test) the first test
    waits until FILE exists: the run before has ended, the machine is as quiet as it
    leaves it. If PID ends first (scripts/test stopped), the run ends instead."""
    gc.collect()
    gc.freeze()
    after = os.environ.pop("RTUPOLL_TEST_AFTER", None)  # (not for what the tests start)
    if after and not session.config.option.collectonly:
        owner, path = after.split(" ", 1)
        if not worker_zygote.hold(path, int(owner)):
            pytest.exit("the run this one waited for is gone", returncode=2)


# scripts/test's parallel (timing) run: the file that tells the timing (alone) run to start
_THEN = os.environ.pop("RTUPOLL_TEST_THEN", "")
# the pytest cache's key for how long each test of the timing group took (seconds)
_TOOK = "rtupoll/timing-took"


def _took(config: pytest.Config) -> dict[str, float]:
    cache = getattr(config, "cache", None)  # (none with -p no:cacheprovider)
    return cache.get(_TOOK, {}) if cache is not None else {}


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    """A timing run keeps how long each of its tests took, for the next one's order."""
    cache = getattr(config, "cache", None)
    if _timing_run(config) and cache is not None and not hasattr(config, "workerinput"):
        took = _took(config)
        for report in terminalreporter.stats.get("passed", []):
            if report.when == "call":
                took[report.nodeid] = round(report.duration, 3)
        cache.set(_TOOK, took)


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session: pytest.Session) -> None:
    """The fork server of this process (tests/forked_cli.py), if a test started it, ends
    with the session, and with it what its children left running.

    With ``RTUPOLL_TEST_THEN=FILE`` (scripts/test's parallel and timing runs) the
    controller, its workers ended, goes to the lowest priority (nice 19: the next run's
    tests come first) and makes FILE: the next run starts while what is left of this one
    (its summary, the workers' and servers' teardown, its exit: 1-1.5 s) ends beside it,
    never ahead of its tests."""
    if _THEN and not hasattr(session.config, "workerinput"):
        os.setpriority(os.PRIO_PROCESS, 0, 19)
        Path(_THEN).touch()
    close_server()


@pytest.fixture(scope="session")
def jitter() -> float:
    """How late a sleeping thread wakes on this machine now: the 99th percentile of 200
    sleeps of 1 ms (seconds). A ``timing`` test's allowance."""
    late = []
    for _ in range(200):
        t = time.monotonic()
        time.sleep(0.001)
        late.append(time.monotonic() - t - 0.001)
    return sorted(late)[197]


@pytest.fixture
def sim() -> Iterator[Callable[..., SimulatedBus]]:
    """Factory: ``bus = sim("huiwen-aq@3", faults=["3:crc"])``; stopped after the test."""
    started: list[SimulatedBus] = []

    def start(*devices: str, **options: Any) -> SimulatedBus:
        bus = simulated_bus(devices, **options).start()
        started.append(bus)
        return bus

    yield start
    for bus in started:
        bus.stop()


@pytest.fixture(autouse=True)
def _no_leaked_simulator() -> Iterator[None]:
    before = set(running())
    yield
    leaked = [bus for bus in running() if bus not in before]
    for bus in leaked:
        bus.stop()
    if leaked:
        pytest.fail(f"the test left {len(leaked)} simulated bus(es) running: "
                    + ", ".join(bus.port for bus in leaked)
                    + " (use the sim fixture or 'with simulated_bus(...)')")


# How long a test waits for a reply that comes (seconds): all the time a busy machine's
# peer (a simulator's thread, a forked command, mbpoll) may need. The reply ends the wait,
# so a passing test never waits it out; only what must NOT come is given a short wait (a
# busy machine can only make that pass). mbpoll's ``-o`` takes at most 10 s.
ANSWERED = 10.0
PATIENT = ("--timeout", f"{ANSWERED:g}")  # rtupoll's options for it
DEAD = 0.1  # the timeout of a device that must not answer: waited out, so short
# A reply judged only when the attempt's time is up (truncated, garbled, not the one asked
# for: the rest may still come) costs its whole timeout: asked with a short one and, while
# nothing at all came in time (a busy machine's peer can be that late), again with ten
# times as long: a wait that only a busy machine pays, and then about what it needed
JUDGED = (0.1, 1.0, ANSWERED)
T = TypeVar("T")


async def judged(ask: Callable[[float], Awaitable[T]]) -> T:
    """``ask(timeout)`` for each of ``JUDGED`` while nothing at all came in time: the
    outcome is the one given with the bytes in hand, never a shorter wait's."""
    for timeout in JUDGED[:-1]:
        try:
            return await ask(timeout)
        except DeviceTimeout as exc:
            if not str(exc).endswith(f"within {timeout:g} s"):  # (else: "ignored: ...")
                raise
    return await ask(JUDGED[-1])


def dead_at(site: Site, dead: Collection[int]) -> Site:
    """``site`` (one bus) with the devices at the ``dead`` addresses asked with ``DEAD``."""
    bus = site.buses[0]
    assert set(dead) <= {d.address for d in bus.devices}
    devices = tuple(dataclasses.replace(d, timeout=DEAD) if d.address in dead else d
                    for d in bus.devices)
    return dataclasses.replace(site, buses=(dataclasses.replace(bus, devices=devices),))


def live_and_dead(tmp_path: Path, port: str) -> Path:
    """A site file: huiwen-aq@3, which answers, and radar-level@4, dead. The dead one's
    timeout is waited out: ``DEAD``; the live one gets ``ANSWERED`` (its answers end the
    waits: ``--timeout`` would give it the dead one's)."""
    site = tmp_path / "site.yaml"
    site.write_text(f"buses:\n  - port: {port}\n    devices:\n"
                    f"      - {{profile: huiwen-aq, address: 3, timeout: {ANSWERED:g}}}\n"
                    f"      - {{profile: radar-level, address: 4, timeout: {DEAD:g}}}\n")
    return site


class RawPort:
    """Exact bytes to and from a pty or an RTU-over-TCP socket."""

    def __init__(self, path: str, baudrate: int | None = None) -> None:
        self.sock: socket.socket | None = None
        if path.startswith("tcp://"):
            host, _, port = path[6:].rpartition(":")
            self.sock = socket.create_connection((host, int(port)), timeout=2)
            self.fd = self.sock.fileno()
        else:
            self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            if baudrate:  # a simulator with wire timing answers only at its own baud
                attrs = termios.tcgetattr(self.fd)
                attrs[4] = attrs[5] = getattr(termios, f"B{baudrate}")
                termios.tcsetattr(self.fd, termios.TCSANOW, attrs)
            termios.tcflush(self.fd, termios.TCIOFLUSH)

    def send(self, data: bytes) -> float:
        """Write ``data``; returns the time it went out (time.monotonic())."""
        t = time.monotonic()
        os.write(self.fd, data)
        return t

    def read(self, n: int | None = None, *, timeout: float | None = None,
             quiet: float = 0.05) -> bytes:
        """Bytes until ``n`` arrived, or (n=None) the line stayed quiet, or ``timeout``.

        By default ``n`` bytes are waited for ``ANSWERED``; without ``n``, 0.5 s: what
        came, or the silence a test asserts."""
        out = b""
        if timeout is None:
            timeout = 0.5 if n is None else ANSWERED
        deadline = time.monotonic() + timeout
        while True:
            now = time.monotonic()
            if (n is not None and len(out) >= n) or now >= deadline:
                return out
            wait = deadline - now if (n is not None or not out) else min(quiet, deadline - now)
            ready, _, _ = select.select([self.fd], [], [], wait)
            if not ready:
                if n is None and out:
                    return out
                continue
            out += os.read(self.fd, 4096)

    def transact(self, request: bytes, n: int | None = None, *,
                 timeout: float | None = None) -> bytes:
        self.send(request)
        return self.read(n, timeout=timeout)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        else:
            os.close(self.fd)


@pytest.fixture
def dtr_states(monkeypatch: pytest.MonkeyPatch) -> list[tuple[bool, bool]]:
    """(DTR, RTS) as each rtupoll-opened port sets them when it opens, in order."""
    from rtupoll.io import own_port

    states: list[tuple[bool, bool]] = []
    real = own_port.Serial._update_dtr_state

    def spy(self: Any) -> None:
        states.append((self._dtr_state, self._rts_state))
        real(self)
    monkeypatch.setattr(own_port.Serial, "_update_dtr_state", spy)
    return states


@pytest.fixture
def raw_port() -> Iterator[Callable[..., RawPort]]:
    """Factory: ``port = raw_port(bus.port[, baudrate])``; closed after the test."""
    opened: list[RawPort] = []

    def open_(path: str, baudrate: int | None = None) -> RawPort:
        port = RawPort(path, baudrate)
        opened.append(port)
        return port

    yield open_
    for port in opened:
        port.close()
