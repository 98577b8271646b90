"""``rtupoll scan`` over a real pty, real pymodbus (through bus.py) and the simulator.

With wire timing (``baudrate=``) the simulator answers only when the client opened the
pty at that speed, so a sweep over several baud rates finds each bus at its own.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import AbstractAsyncContextManager
from pathlib import Path
from typing import Any

import pytest
from cli_runner import rtupoll
from forked_cli import rtupoll_popen, rtupoll_run

from rtupoll.config.library import load_library
from rtupoll.config.site import load_site
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.jobs.scan import Found, Setting, presence_probes, probe_timeout, sweep
from rtupoll.rtu import Framing
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
FIXTURES = Path(__file__).parents[1] / "fixtures" / "scan"
SEEDS = ["net-irnet-pro@3", "radar-level@7", "huiwen-aq@12", "co2meter-an117@20",
         "banner-ez-array@31"]
RTUPOLL = [sys.executable, "-m", "rtupoll"]


# the simulator's thread may answer 100 ms late on a busy machine: twice the default
# turnaround margin, so identification does not depend on the machine's load (the
# derived margins themselves are exact in virtual time, tests/jobs/test_jobs_scan.py)
PATIENT = ("--turnaround", "0.15")


def scan_json(*args: str) -> tuple[int, list[dict[str, Any]], str]:
    result = rtupoll("scan", "--format", "json", *args)
    lines = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    return result.returncode, lines, result.stderr


def test_five_seed_devices_on_one_bus_are_found_and_identified(sim: Sim) -> None:
    bus = sim(*SEEDS, baudrate=115200)
    # their addresses only: a silent one costs its timeout and, once the sweep ends, the
    # wait for late answers (about 0.8 s in all); empty addresses are the empty range's
    # test below, and silent ones around devices the written site file's (`timing`)
    code, found, _ = scan_json("--port", bus.port, "--addresses", "3,7,12,20,31",
                               "--baudrate", "115200", *PATIENT)
    assert code == 0
    assert [(f["address"], f["profile"], f["status"]) for f in found] == [
        (3, "net-irnet-pro", "identified"), (7, "radar-level", "identified"),
        (12, "huiwen-aq", "identified"), (20, "co2meter-an117", "identified"),
        (31, "banner-ez-array", "identified")]
    assert all(f["baudrate"] == 115200 and f["evidence"] for f in found)


# identification reads the real pty against the sweep's real timeouts: seen to miss a
# reply beside 4 workers on a loaded machine (load 20 on 2 cores), so it runs alone
@pytest.mark.timing
def test_found_at_the_simulators_baud_not_the_first_tried(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", baudrate=19200)
    code, found, _ = scan_json("--port", bus.port, "--addresses", "3-4",
                               "--baudrate", "9600,19200", *PATIENT)
    assert code == 0
    assert {(f["address"], f["baudrate"], f["profile"]) for f in found} == {
        (3, 19200, "huiwen-aq"), (4, 19200, "radar-level")}


def test_a_device_with_no_profile_is_listed_as_unknown_then_identified_with_it(sim: Sim
                                                                              ) -> None:
    bus = sim("acme-meter@5", "huiwen-aq@6", profile_dirs=[FIXTURES], baudrate=115200)
    code, found, _ = scan_json("--port", bus.port, "--addresses", "5-6", "--baudrate", "115200",
                               *PATIENT)
    assert code == 0
    unknown, huiwen = found
    assert (unknown["address"], unknown["status"], unknown["profile"]) == (5, "unknown", None)
    assert any(a.startswith("input 0x0001:") for a in unknown["answers"])
    assert huiwen["profile"] == "huiwen-aq"
    _, found, _ = scan_json("--port", bus.port, "--addresses", "5", "--baudrate", "115200",
                            "--profiles", str(FIXTURES), *PATIENT)
    assert found[0]["profile"] == "acme-meter"


def test_an_empty_range_costs_no_more_than_the_derived_timeouts(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", baudrate=115200)
    library = sorted(load_library().profiles.values(), key=lambda p: p.id)
    setting, margin, probes = Setting(115200), 0.03, presence_probes(library)

    def open_bus(s: Setting) -> AbstractAsyncContextManager[Bus]:
        return Bus(PortSettings(bus.port, s.baudrate, deassert_dtr=True), drain=0.0)

    found: list[Found] = []
    started = time.monotonic()
    asyncio.run(sweep(open_bus, [setting], range(100, 110), library, margin=margin,
                      probes=probes, found=found))
    elapsed = time.monotonic() - started
    framing = Framing(115200)
    derived = 10 * probe_timeout(framing, 1, margin)
    assert found == []
    # never less than the derived timeouts (that it is not more is a rule about time:
    # exact in virtual time, tests/jobs/test_jobs_scan.py; here a busy machine adds to it)
    assert derived * 0.95 <= elapsed
    assert len([w for w in bus.wire if w.direction == "in"]) == 10  # one probe each


@pytest.mark.timing  # (as above: a sweep that identifies by the real clock)
def test_the_written_site_file_loads_and_polls(sim: Sim, tmp_path: Path) -> None:
    # silent addresses before, between and after three devices, at a speed all of them
    # run at (identifying a device is 5 to 15 round trips: 19200 baud, not 9600, took
    # 2.0 s instead of 2.75)
    bus = sim("net-irnet-pro@2", "banner-ez-array@3", "radar-level@5", baudrate=19200)
    site = tmp_path / "site.yaml"
    result = rtupoll("scan", "--port", bus.port, "--addresses", "1-6",
                     "--baudrate", "19200", "--write-config", str(site),
                     *PATIENT)
    assert result.returncode == 0, result.stderr
    loaded = load_site(site)
    assert [(d.profile.id, d.address) for _, d in loaded.devices()] == [
        ("net-irnet-pro", 2), ("banner-ez-array", 3), ("radar-level", 5)]
    poll = rtupoll("poll", "--config", str(site), "--once", "--format", "json")
    assert poll.returncode == 0, poll.stderr
    records = [json.loads(line) for line in poll.stdout.splitlines()]
    assert {r["device"] for r in records} == {"net-irnet-pro@2", "banner-ez-array@3",
                                              "radar-level@5"}
    assert all(r["status"] == "ok" for r in records)


def test_ctrl_c_prints_what_was_found_so_far(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", baudrate=4800)
    proc = subprocess.Popen([*RTUPOLL, "scan", "--port", bus.port, "--baudrate", "4800",
                             "--format", "json", *PATIENT], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # (identified: see PATIENT)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and \
            sum(w.direction == "in" and w.data[0] > 3 for w in bus.wire) < 2:
        time.sleep(0.05)  # until the sweep is past address 3
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 130
    assert json.loads(out.splitlines()[0])["profile"] == "huiwen-aq"
    assert "results so far" in err


def test_progress_bar_only_on_a_terminal(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", baudrate=115200)
    # one address: the bar is drawn when it starts and when it stops; a silent address
    # would only add its timeout and the wait for late answers (29 of them: 5 s)
    args = [*RTUPOLL, "scan", "--port", bus.port, "--addresses", "1", "--baudrate",
            "115200", "--format", "json"]
    piped = rtupoll_run(args, capture_output=True, text=True, timeout=60)
    assert piped.returncode == 0 and "\x1b[" not in piped.stderr
    master, slave = os.openpty()
    env = {**os.environ, "COLUMNS": "120", "TERM": "xterm"}
    proc = rtupoll_popen(args, stdout=subprocess.PIPE, stderr=slave, env=env)
    os.close(slave)
    out, _ = proc.communicate(timeout=60)
    seen = b""
    try:
        while chunk := os.read(master, 65536):
            seen += chunk
    except OSError:
        pass
    os.close(master)
    assert proc.returncode == 0 and json.loads(out.decode().splitlines()[0])["address"] == 1
    assert b"found" in seen and b"\x1b[" in seen  # the live bar, drawn with escapes


def test_an_identification_read_a_present_device_is_slow_to_answer_is_asked_again(
        sim: Sim) -> None:
    """The PZEM-016 named "unknown" on a loaded machine: its identification read timed
    out once. A unit that answered is asked such a read once more, waiting longer, so a
    slow answer is no evidence against a profile (an empty address still costs one
    timeout). Here every identification read (the requests after the presence probes)
    is answered 0.2 s late, past the probe's wait: still identified."""
    after = len(presence_probes(list(load_library().profiles.values()))) + 1
    bus = sim("peacefair-pzem016@2", faults=[f"2:slow=0.2@{after}-"], tick=None)
    code, found, err = scan_json("--port", bus.port, "--addresses", "2", "--baudrate",
                                 "9600")
    assert code == 0, err
    assert [(f["address"], f["profile"], f["status"]) for f in found] == [
        (2, "peacefair-pzem016", "identified")]
