"""README.md's Windows commands (between ``<!-- windows:begin -->`` and ``<!-- windows:end
-->``) as printed, on Windows's CPython 3.13 under Wine: each ``.venv\\Scripts\\python -m
rtupoll ...`` line runs as ``python.exe -m rtupoll ...``, with ``COM3`` the demo's line 1
(9600 8N1: net-irnet-pro@1, radar-level@2, huiwen-aq@3, banner-ez-array@5, as the docs'
examples have it); one that runs until stopped gets a Ctrl-C once it has shown readings,
and ends 0. The set-up lines (``py -m venv``, ``pip install``) cannot run here (the
embeddable build has no venv and no pip: scripts/windows-setup unpacks the wheels
instead): they are checked to be just those.
"""

from __future__ import annotations

import re
import shlex
from collections.abc import Callable
from pathlib import Path

import pytest
from wine import Wine, setup

from rtupoll.sim.runner import SimulatedBus

pytestmark = pytest.mark.windows
Sim = Callable[..., SimulatedBus]
README = Path(__file__).resolve().parents[2] / "README.md"
RUN = ".venv\\Scripts\\python -m rtupoll "
SETUP = ("py -m venv .venv", ".venv\\Scripts\\pip install ")
LINE1 = ("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "banner-ez-array@5")


def commands() -> list[str]:
    text = README.read_text(encoding="utf-8")
    block = re.search(r"<!-- windows:begin -->\n```powershell\n(.*?)```\n<!-- windows:end -->",
                      text, re.S)
    assert block, "README.md has no windows:begin/end block"
    return [line.split("  #")[0].strip() for line in block.group(1).splitlines()
            if line.strip()]


def test_the_set_up_lines_are_only_venv_and_pip() -> None:
    lines = commands()
    assert [line for line in lines if not line.startswith(RUN)] == [
        line for line in lines if line.startswith(SETUP)], lines
    assert sum(line.startswith(RUN) for line in lines) >= 3, lines


def test_the_readmes_windows_commands_run_as_printed(sim: Sim, tmp_path: Path) -> None:
    setup()
    bus = sim(*LINE1, link=str(tmp_path / "com3"), tick=None)
    runs = [shlex.split(line[len(RUN):]) for line in commands() if line.startswith(RUN)]
    with Wine(ports={"COM3": tmp_path / "com3"}) as wine:
        for args in runs:
            if "poll" in args[:1] and "--once" not in args:  # until Ctrl-C: a live table
                with wine.running(*args) as live:
                    live.wait(lambda lines: any("co2" in line for line in lines))
                    code, err = live.interrupt()
                assert code == 0, (args, err)
            else:
                ran = wine.rtupoll(*args)
                assert ran.returncode == 0, (args, ran)
                if args[:1] == ["read"]:  # the simulator's value, in the table
                    co2 = str(bus.get(3, "co2").value)
                    assert any(line.split("|")[1:3] and line.split("|")[1].strip() == "co2"
                               and line.split("|")[2].strip() == co2
                               for line in ran.stdout.splitlines()), ran.stdout
