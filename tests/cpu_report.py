"""``--cpu-report[=N]``: where a run's CPU goes (tests/README.md, "How fast").

Each test's CPU time (user + system, from ``getrusage``) of the process that runs it and
of the child processes it waited for (the ``rtupoll`` subprocesses, peers), setup, call
and teardown together; with pytest-xdist each worker sends its figures to the main
process, which also gets what every worker spent before its first test (start-up,
imports and collection). At the end: the run's totals, the N most expensive tests and
files (30 by default), and the children's share.

    .venv/bin/python -m pytest -q -n 2 --cpu-report=40 tests/cli
"""

from __future__ import annotations

import resource
import sys
import time
from collections import defaultdict
from collections.abc import Generator
from typing import Any

import pytest

_KEY = "cpu_report"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--cpu-report", action="store", nargs="?", const="30", default=None,
                     metavar="N", help="report the CPU time of the N costliest tests")


def _cpu() -> tuple[float, float]:
    me = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    # and the commands forked for this process (tests/forked_cli.py: the fork server's
    # children, not this process's)
    forked = sys.modules.get("forked_cli")
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime + (
        forked.FORKED_CPU[0] if forked is not None else 0.0)


class _Report:
    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.top = int(config.getoption("--cpu-report"))
        self.tests: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
        self.start: list[tuple[float, float]] = []  # each worker's before its first test
        self.first: tuple[float, float] | None = None
        # a worker's (seconds from its first test to its last, seconds in tests)
        self.began = 0.0
        self.busy = 0.0
        self.workers: list[tuple[float, float]] = []

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_protocol(self, item: pytest.Item) -> Generator[None, Any, Any]:
        if self.first is None:
            self.first = _cpu()
            self.began = time.monotonic()
            if hasattr(self.config, "workeroutput"):
                self.config.workeroutput[_KEY] = self.first
        try:
            return (yield)
        finally:
            if hasattr(self.config, "workeroutput"):
                self.config.workeroutput[_KEY + "_wall"] = (time.monotonic() - self.began,
                                                            self.busy)

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_setup(self, item: pytest.Item) -> Generator[None, Any, Any]:
        return (yield from self._measure(item))

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_call(self, item: pytest.Item) -> Generator[None, Any, Any]:
        return (yield from self._measure(item))

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_teardown(self, item: pytest.Item) -> Generator[None, Any, Any]:
        return (yield from self._measure(item))

    def _measure(self, item: pytest.Item) -> Generator[None, Any, Any]:
        me, kids = _cpu()
        try:
            return (yield)
        finally:
            me2, kids2 = _cpu()
            # each phase's report carries the entries of the phases before it too: the
            # main process takes the last one
            item.user_properties.append((_KEY, (len(item.user_properties), me2 - me,
                                                kids2 - kids)))

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if hasattr(self.config, "workeroutput"):
            self.busy += report.duration
            return  # the main process counts
        ours = [v for name, v in report.user_properties if name == _KEY]
        if ours:  # this phase's entry is the last one
            _, me, kids = ours[-1]
            row = self.tests[report.nodeid]
            row[0] += me
            row[1] += kids
        self.tests[report.nodeid][2] += report.duration

    @pytest.hookimpl(optionalhook=True)  # pytest-xdist's: not there without it
    def pytest_testnodedown(self, node: Any, error: Any) -> None:
        output = getattr(node, "workeroutput", {})
        start = output.get(_KEY)
        if start is not None:
            self.start.append(tuple(start))
        if output.get(_KEY + "_wall") is not None:
            self.workers.append(tuple(output[_KEY + "_wall"]))

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if hasattr(self.config, "workeroutput"):
            return
        if not self.start and self.first is not None:
            self.start.append(self.first)
        tr = terminalreporter
        me = sum(r[0] for r in self.tests.values())
        kids = sum(r[1] for r in self.tests.values())
        start = sum(a + b for a, b in self.start)
        tr.write_sep("=", "CPU report (CPU-s: in the test process + its children)")
        tr.write_line(f"tests: {me:.1f} + children {kids:.1f} = {me + kids:.1f} CPU-s over "
                      f"{len(self.tests)} tests; before the first test: {start:.1f} CPU-s "
                      f"in {len(self.start)} process(es); total {me + kids + start:.1f}")
        if self.workers:
            tr.write_line("workers, from the first test to the last: " + ", ".join(
                f"{w:.0f} s ({busy / w:.0%} in tests)" for w, busy in sorted(self.workers)))
        files: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0, 0.0])
        for nodeid, (a, b, wall) in self.tests.items():
            f = files[nodeid.split("::")[0]]
            f[0] += a
            f[1] += b
            f[2] += wall
            f[3] += 1
        tr.write_line(f"{'CPU-s':>7} {'self':>6} {'kids':>6} {'wall':>6}  file (tests)")
        for path, (a, b, wall, n) in sorted(files.items(), key=lambda kv: -kv[1][0] - kv[1][1]
                                            )[:self.top]:
            tr.write_line(f"{a + b:7.2f} {a:6.2f} {b:6.2f} {wall:6.1f}  {path} ({int(n)})")
        tr.write_line(f"{'CPU-s':>7} {'self':>6} {'kids':>6} {'wall':>6}  test")
        for nodeid, (a, b, wall) in sorted(self.tests.items(), key=lambda kv: -kv[1][0] - kv[1][1]
                                           )[:self.top]:
            tr.write_line(f"{a + b:7.2f} {a:6.2f} {b:6.2f} {wall:6.1f}  {nodeid}")


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--cpu-report") is not None:
        config.pluginmanager.register(_Report(config), "cpu-report-collector")
