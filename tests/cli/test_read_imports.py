"""A one-shot read imports only what it uses: no simulator, scheduler or live table, no
rich on the machine-readable paths, no csv module but for the csv format, no logging
(nothing logs on a read that goes well, and the end does not import it to shut it down),
no YAML parser
(nor pickle.py: the C unpickler alone) once the profile is in the compiled profile
cache, and no event loop or async transport (asyncio, pymodbus): it reads on the
blocking bus (measured with ``python -X importtime``)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

import pytest

from rtupoll.config.library import load_one
from rtupoll.sim.runner import SimulatedBus

UNUSED = ("rich", "rtupoll.sim", "rtupoll.jobs.scheduler", "rtupoll.ui.live", "rtupoll.config.site",
          "rtupoll.jobs.commission", "yaml", "asyncio", "pymodbus", "rtupoll.io.bus", "logging")


def imported(*argv: str) -> set[str]:
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "rtupoll", *argv],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines()
            if line.startswith("import time:") and line.count("|") == 2}


def loaded(modules: set[str], package: str) -> bool:
    return any(m == package or m.startswith(package + ".") for m in modules)


@pytest.mark.parametrize("fmt", ["json", "csv"])
def test_json_and_csv_reads_import_nothing_they_do_not_use(
        sim: Callable[..., SimulatedBus], fmt: str) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    load_one("huiwen-aq")  # the profile in the cache (the test run's own: conftest.py)
    modules = imported("read", "--port", bus.port, "--format", fmt, "huiwen-aq@1", "co2")
    assert "rtupoll.io.syncbus" in modules and "rtupoll.model.planner" in modules  # it read
    assert [p for p in UNUSED if loaded(modules, p)] == []
    assert ("csv" in modules) is (fmt == "csv")  # the csv module for the csv format only
    # the profile came from the cache through the C unpickler, without pickle.py around it
    assert "_pickle" in modules and "pickle" not in modules


def test_the_table_for_people_does_load_rich(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    modules = imported("read", "--port", bus.port, "huiwen-aq@1", "co2")
    assert loaded(modules, "rich") and not loaded(modules, "rtupoll.sim")


def test_the_blocking_bus_compiles_no_dataclass_method_at_import() -> None:
    """The bus's messages, line and transaction classes are declared with ``@frozen`` and
    ``@mutable`` (rtupoll/frozen.py): importing them writes none of their methods (as
    dataclasses these compiled 78 methods, about 13 ms of a read's start)."""
    script = """if True:
        import dataclasses, sys
        import rtupoll.io.syncbus
        from rtupoll.io import own_port
        from rtupoll.rtu import line, messages, transaction
        classes = [c for m in (messages, line, transaction, own_port) for c in vars(m).values()
                   if dataclasses.is_dataclass(c) and c.__module__ == m.__name__]
        eager = [c.__name__ for c in classes
                 if not c.__init__.__code__.co_filename.endswith("frozen.py")]
        print(len(classes) >= 20, eager)
    """
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, timeout=60).stdout
    assert out == "True []\n"
