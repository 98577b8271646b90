"""Parity as the wire has it (issue 47: an 8E1 meter answered a master at 8N1 or 8O1, and
``scan --parity N,E`` listed it twice). A pty has no parity bit; the master marks the
parity it set (``pty_parity.pty_parity``: INPCK, and PARODD for odd, the flags libmodbus
sets too), and the simulator lets only the devices at that parity hear a request. Real
masters on the simulator's pty: rtupoll (read, scan) and mbpoll."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import termios
import tty
from collections.abc import Callable

import pytest
from cli_runner import rtupoll
from conftest import PATIENT

from rtupoll.io import pty_parity
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus
from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
METER = "schneider-iem3155@1"  # 8E1 at 19200
MBPOLL = shutil.which("mbpoll")


@pytest.mark.parametrize("parity", ["N", "E", "O"])
def test_a_pty_opened_at_a_parity_says_so_from_its_other_side(parity: str) -> None:
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        with SyncBus(PortSettings(os.ttyname(slave), baudrate=19200, parity=parity)):
            assert pty_parity.pty_parity_of(slave) == parity
            assert not termios.tcgetattr(slave)[2] & termios.PARENB  # (no parity bit)
    finally:
        os.close(master)
        os.close(slave)


def test_the_meter_answers_only_a_master_at_its_parity(sim: Sim) -> None:
    bus = sim(METER, tick=None)
    at = ["read", "-p", bus.port, METER, "frequency", "--format", "json"]
    ok = rtupoll(*at, *PATIENT)  # the profile's 8E1
    assert ok.returncode == 0, (ok.stdout + ok.stderr)
    assert json.loads(ok.stdout)["value"] == pytest.approx(bus.get(1, "frequency").value)
    for wrong in ("N", "O"):
        result = rtupoll(*at, "--parity", wrong, "--timeout", "0.2")
        assert result.returncode == 4, result.stderr  # no reply: noise to the meter
        assert f"sent at parity {wrong}, the device runs at E" in bus.engine.why_silent


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (scripts/setup does it)")
def test_mbpoll_is_answered_at_even_parity_only(sim: Sim) -> None:
    bus = sim(METER, tick=None)
    register = 3110  # frequency (wire 3109), a float: two registers

    def mbpoll(parity: str, timeout: str) -> subprocess.CompletedProcess[str]:
        assert MBPOLL is not None
        return subprocess.run([MBPOLL, "-m", "rtu", "-b", "19200", "-P", parity, "-1",
                               "-o", timeout, "-a", "1", "-t", "4", "-r", str(register),
                               "-c", "2", bus.port], capture_output=True, text=True,
                              timeout=60, check=False)

    even = mbpoll("even", "10")
    assert even.returncode == 0 and "Read" not in even.stdout + even.stderr, even
    assert bus.registers(1, Table.HOLDING, register - 1, 2) != (0, 0)
    none = mbpoll("none", "0.3")
    assert "timed out" in (none.stdout + none.stderr).lower() or none.returncode != 0


def test_scan_over_two_parities_lists_the_meter_once_and_names_parity_when_empty(
        sim: Sim) -> None:
    bus = sim(METER, tick=None)
    result = rtupoll("scan", "-p", bus.port, "--addresses", "1",
                     "--baudrate", "19200", "--parity", "N,E", "--turnaround",
                     "0.15", "--format", "json")
    assert result.returncode == 0, (result.stdout + result.stderr)
    found = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(f["address"], f["parity"], f["profile"]) for f in found] == [
        (1, "E", "schneider-iem3155")]
    empty = rtupoll("scan", "-p", bus.port, "--addresses", "1",
                    "--baudrate", "19200")  # parity N only (the default)
    assert empty.returncode == 4
    line = empty.stderr.strip().splitlines()[-1]
    assert "19200 baud, parity N" in line and "not tried: parity E, O" in line
    assert "run at parity E: add --parity N,E" in line  # named by the profiles that do
    assert "schneider-iem3155" in line or " ... run at parity E" in line
