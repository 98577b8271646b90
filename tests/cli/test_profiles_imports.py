"""``profiles list --format json`` (what scripts and the tests read) prints no table, so it
loads no rich, simulator, scheduler or Modbus library; the table for people does load
rich (measured with ``python -X importtime``)."""

from __future__ import annotations

import json
import subprocess
import sys

UNUSED = ("rich", "rtupoll.sim", "rtupoll.jobs.scheduler", "rtupoll.config.site",
          "asyncio", "pymodbus", "rtupoll.io.bus")


def imported(*argv: str) -> tuple[set[str], str]:
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "rtupoll", *argv],
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return ({line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines()
             if line.startswith("import time:") and line.count("|") == 2}, proc.stdout)


def loaded(modules: set[str], package: str) -> bool:
    return any(m == package or m.startswith(package + ".") for m in modules)


def test_a_json_listing_imports_nothing_it_does_not_use() -> None:
    modules, out = imported("profiles", "list", "--format", "json")
    assert "huiwen-aq" in {json.loads(line)["id"] for line in out.splitlines()}  # it listed
    assert [p for p in UNUSED if loaded(modules, p)] == []


def test_the_table_for_people_does_load_rich() -> None:
    modules, out = imported("profiles", "list")
    assert "huiwen-aq" in out and loaded(modules, "rich")
