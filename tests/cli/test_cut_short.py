"""Commands cut short say what may have happened on the device: the real CLI as a
process of its own, SIGINT (as a Ctrl-C sends it) or a port that goes away at a moment
the simulator's wire and rtupoll's own log line fix, against simulated devices."""

from __future__ import annotations

import json
import os
import re
import select
import signal
import subprocess
import time
from collections.abc import Callable

import pytest
from forked_cli import RTUPOLL, rtupoll_popen

from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
HANG = 60.0  # hang guards: what is waited for comes, or the test is broken
# the huiwen module at 3 answers its first two requests (the read of its address, the
# write), then its replies come 20 s late: set-address is verifying when it is cut short
SLOW_AFTER_WRITE = ["3:slow=20@3-"]


def stderr_until(proc: subprocess.Popen[bytes], text: bytes) -> bytes:
    assert proc.stderr is not None
    seen, deadline = b"", time.monotonic() + HANG
    while text not in seen:
        assert time.monotonic() < deadline and proc.poll() is None, seen
        if select.select([proc.stderr], [], [], 0.2)[0]:
            seen += os.read(proc.stderr.fileno(), 65536)
    return seen


def set_address(bus: SimulatedBus, fmt: str) -> subprocess.Popen[bytes]:
    return rtupoll_popen([RTUPOLL, "set-address", "-p", bus.port, "huiwen-aq@3", "12",
                          "--yes", "--format", fmt], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_set_address_interrupted_after_the_write_names_both_addresses(
        sim: Sim, fmt: str) -> None:
    bus = sim("huiwen-aq@3", faults=SLOW_AFTER_WRITE, tick=None)
    proc = set_address(bus, fmt)
    seen = stderr_until(proc, b"written (echo); verifying")
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=HANG)
    err = seen + err
    assert proc.returncode == 130, err
    again = f"run 'rtupoll set-address -p {bus.port} huiwen-aq@3 12' again to check both"
    if fmt == "json":
        (record,) = [json.loads(line) for line in out.decode().splitlines()]
        assert record["status"] == "written, unverified" and record["exit_code"] == 130
        assert (record["address"], record["new"]) == (3, 12)
        detail = record["detail"]
    else:
        (line,) = out.decode().splitlines()
        detail = line.removeprefix("huiwen-aq@3 -> 12: ")
    assert detail.startswith("interrupted after the write: the device may be at 12 or "
                             "still at 3; ") and again in detail, out
    assert err.decode().endswith("rtupoll: interrupted\n")
    # and it is so: the device took the write (it answers at 12 now, late)
    assert [f for f in bus.wire if f.direction == "in" and f.data[0] == 12]


@pytest.mark.parametrize("fmt", ["text", "json"])
def test_set_address_whose_port_goes_away_after_the_write_names_both_addresses(
        sim: Sim, fmt: str) -> None:
    bus = sim("huiwen-aq@3", faults=SLOW_AFTER_WRITE, tick=None)
    proc = set_address(bus, fmt)
    seen = stderr_until(proc, b"verifying")
    bus.stop()  # the adapter unplugged while rtupoll waits for the verification
    out, err = proc.communicate(timeout=HANG)
    lines = (seen + err).decode().splitlines()
    assert proc.returncode == 3, lines
    # the port is found gone while a reply is awaited or between two requests: either way
    said = re.compile(re.escape(bus.port) + r" went away( during the transaction)?: the "
                      r"write may have gone out, so the device may be at 12 or still at "
                      r"3; run 'rtupoll set-address")
    assert said.match(lines[-1].removeprefix("rtupoll: ")), lines
    if fmt == "json":
        (record,) = [json.loads(line) for line in out.decode().splitlines()]
        assert record["status"] == "failed" and record["exit_code"] == 3
        assert said.match(record["detail"]), record
    else:
        assert out == b""


def test_a_write_whose_port_goes_away_after_the_request_left_says_it_may_have_landed(
        sim: Sim) -> None:
    bus = sim("banner-ez-array@5", faults=["5:slow=20"], tick=None)  # no reply in time
    proc = rtupoll_popen([RTUPOLL, "write", "-p", bus.port, "banner-ez-array@5",
                          "measurement_1_mode=TBB", "--yes"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    deadline = time.monotonic() + HANG
    while not [f for f in bus.wire if f.direction == "in" and f.data[:1] == b"\x05"]:
        assert time.monotonic() < deadline and proc.poll() is None, "the write never left"
        time.sleep(0.01)
    bus.stop()  # the port goes away while rtupoll waits for the write's reply
    _, err = proc.communicate(timeout=HANG)
    assert proc.returncode == 3, err
    (line,) = err.decode().splitlines()
    assert line.startswith(f"rtupoll: {bus.port} went away during the transaction, after "
                           "sending measurement_1_mode = TBB"), line
    assert line.endswith("the write may have been applied; once the port is back, read the "
                         f"device to know: rtupoll read -p {bus.port} banner-ez-array@5 "
                         "measurement_1_mode"), line


def test_a_ctrl_c_just_after_a_writes_table_is_never_a_silent_kill(sim: Sim) -> None:
    """Once the table is out the command has done its work; a Ctrl-C then (while
    Python would tear itself down, and run no handler) gets a line and the command's
    own status, never death by the signal."""
    bus = sim("banner-ez-array@5", tick=None)
    endings = []
    for delay in (0.0, 0.001, 0.003, 0.01, 0.03):
        proc = subprocess.Popen([RTUPOLL, "write", "-p", bus.port, "banner-ez-array@5",
                                 "measurement_1_mode=TBB", "--yes"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None
        out, deadline = b"", time.monotonic() + HANG
        while b"measurement_1_mode" not in out:  # the table's row: the write is done
            assert time.monotonic() < deadline, out
            chunk = os.read(proc.stdout.fileno(), 65536)
            if not chunk:
                break
            out += chunk
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=HANG)
        endings.append((proc.returncode, err.decode()))
    for code, err in endings:
        assert code >= 0, endings  # not killed by SIGINT
        assert code == 0 or err.startswith("rtupoll: interrupted"), endings
        if code == 0 and err:  # the command had ended: it says so
            assert err == ("rtupoll: interrupted after the command had ended (exit 0): "
                           "what it printed is complete\n"), endings
    # (whether a Ctrl-C finds the command still there is the machine's race: on a fast
    # one every process may have ended first; none may end by the signal either way)
