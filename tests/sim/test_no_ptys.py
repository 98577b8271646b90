"""Where there are no pseudo-terminals (Windows): ``rtupoll simulate`` on a pty says so in
one line and points to ``--tcp``; ``poll --simulate`` serves its lines over TCP instead and
reads them as on a pty. (The Windows group runs the same on Windows itself; here the
absence is the only thing made up: ``sim.server.PTYS``, what ``os`` offers.)"""

from __future__ import annotations

import json

import pytest
from cli_runner import rtupoll
from conftest import PATIENT

from rtupoll.sim import server


@pytest.fixture
def no_ptys(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server, "PTYS", False)


@pytest.mark.parametrize("args", [("huiwen-aq@3",), ("--tap", "tap", "huiwen-aq@3")])
def test_simulate_on_a_pty_is_one_line_naming_tcp(no_ptys: None, args: tuple[str, ...]
                                                  ) -> None:
    ran = rtupoll("simulate", *args)
    assert ran.returncode == 2
    assert ran.stderr.count("\n") == 1, ran.stderr
    assert "only POSIX systems (Linux, macOS) have" in ran.stderr
    assert "--tcp 127.0.0.1:5020" in ran.stderr


def test_poll_simulate_serves_its_lines_over_tcp(no_ptys: None) -> None:
    ran = rtupoll("poll", "--simulate", "--once", "--format", "json", *PATIENT)
    assert ran.returncode == 0, ran.stderr
    records = [json.loads(line) for line in ran.stdout.splitlines()]
    assert {r["profile"] for r in records} == {"net-irnet-pro", "radar-level", "huiwen-aq",
                                               "co2meter-an117", "banner-ez-array"}
    assert {r["status"] for r in records} == {"ok"}  # (a pty asked for would be exit 2)
