"""The README's commissioning script, extracted as a reader would copy it, run twice
against the simulator the README names for it: the second run must find everything
already done."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from rtupoll.sim.runner import SimulatedBus

README = Path(__file__).parents[2] / "README.md"


def script() -> str:
    text = README.read_text(encoding="utf-8")
    m = re.search(r"<!-- commissioning:begin -->\n```sh\n(.*?)```\n<!-- commissioning:end -->",
                  text, re.S)
    assert m, "README.md lost its commissioning script markers"
    return m.group(1)


def simulator() -> list[str]:
    """The devices of the simulator the README's prose names for the script, checked to be
    on the port it says to export."""
    text = README.read_text(encoding="utf-8")
    prose = " ".join(text.split("<!-- commissioning:begin -->")[0]
                     .rsplit("## Commissioning", 1)[1].split())
    said = re.search(r"`rtupoll simulate ([^`]+) --link (\S+)`", prose)
    assert said, prose
    assert f"`export RTUPOLL_PORT={said.group(2)}`" in prose
    return said.group(1).split()


def test_the_script_is_five_lines() -> None:
    assert len(script().splitlines()) == 5


def test_the_readme_script_commissions_the_simulated_bus_and_is_safe_to_rerun(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim(*simulator(), tick=None,
              sets=["huiwen-aq@2.co2=612", "radar-level@1.level_cm=42"])
    # 0.1 s is what each ask of an address that no longer answers costs (the runs ask
    # the old ones); a device that answers is asked again if it did not within it
    # (RTUPOLL_RETRIES): a busy machine's simulator thread was once later than 0.1 s
    env = {**os.environ, "RTUPOLL_PORT": bus.port, "RTUPOLL_TIMEOUT": "0.1",
           "RTUPOLL_RETRIES": "1",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for run in ("first", "again"):
        proc = subprocess.run(["bash", "-eu", "-o", "pipefail", "-c", script()], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, f"{run}: {proc.stderr}"
        report = [json.loads(line) for line in
                  (tmp_path / "report.json").read_text().splitlines()]
        want = "changed" if run == "first" else "already done"
        assert [(r["profile"], r["new"], r["status"]) for r in report] == [
            ("radar-level", 11, want), ("huiwen-aq", 12, want)]
        assert "01 06 03 F4 00 0B 89 BB" in proc.stdout  # the dry run's FC06 to the radar
        co2 = next(json.loads(line) for line in proc.stdout.splitlines()
                   if line.startswith('{"device":"huiwen-aq@12"'))
        assert co2["field"] == "co2" and co2["value"] == 612
        assert "level_cm" in proc.stdout and "42" in proc.stdout  # the table for people
    assert bus.addresses() == {"radar-level@1": 11, "huiwen-aq@2": 12}
