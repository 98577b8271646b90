"""``rtupoll poll`` streaming from a simulated bus with one faulty device, for every fault kind.

Three devices of the same profile share the bus, each pinned to values that encode
its own address, so a reply given to the wrong request (a late answer, another id's
frame) would show up as a value that belongs to another device. For each fault the
real command runs as a subprocess (as a user would run it), streaming JSON until
the live devices have been read many times and the faulty one has had its chances;
then it gets SIGINT and must stop cleanly: exit 0, nothing on stderr, every line whole.
"""

from __future__ import annotations

import asyncio
import json
import queue
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import ANSWERED
from forked_cli import rtupoll_popen
from virtual import simulated

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.records import reading_record

UNITS = (1, 2, 3)
TIMEOUT = 0.25  # seconds; the profile's 0.5 s would only make the tests slower
FAULTY = 2
PINNED = {"co2": 1000, "pm25": 100, "temperature": 20, "humidity": 40}  # + the unit address


def pinned(unit: int) -> dict[str, int]:
    return {name: base + unit for name, base in PINNED.items()}


def start_bus(sim: Callable[..., SimulatedBus], *faults: str) -> SimulatedBus:
    bus = sim(*(f"huiwen-aq@{u}" for u in UNITS), faults=faults, seed=1, turnaround=0.002)
    for u in UNITS:
        for name, value in pinned(u).items():
            bus.set(u, name, value)
    return bus


class PollProcess:
    """``rtupoll poll --format json ...`` as a subprocess, its records read as they come."""

    def __init__(self, *args: str) -> None:
        cmd = [sys.executable, "-m", "rtupoll", "poll", "--format", "json", *args]
        self.proc = rtupoll_popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.records: list[dict[str, Any]] = []
        self.raw: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def _take(self, line: str) -> None:
        self.raw.append(line)
        self.records.append(json.loads(line))

    def until(self, done: Callable[[list[dict[str, Any]]], bool], limit: float) -> bool:
        """Read records until ``done(records)`` or ``limit`` seconds; whether it was done."""
        deadline = time.monotonic() + limit
        while not done(self.records):
            if time.monotonic() > deadline:
                return False
            try:
                line = self._lines.get(timeout=0.2)
            except queue.Empty:
                continue
            if line is None:
                return done(self.records)
            self._take(line)
        return True

    def stop(self, sig: int = signal.SIGINT) -> tuple[str, int]:
        """Signal it, collect the rest; (stderr, exit status). Every line must be whole."""
        self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout=30)  # (hang guards: its exit, its output's end)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        while (line := self._lines.get(timeout=30)) is not None:
            self._take(line)  # whatever came after the signal is whole lines too
        assert all(line.endswith("\n") for line in self.raw), "a partial line was written"
        assert self.proc.stderr is not None and self.proc.stdout is not None
        stderr = self.proc.stderr.read()
        self.proc.stderr.close()
        self.proc.stdout.close()
        return stderr, code


def stream(port: str, *, until: Callable[[list[dict[str, Any]]], bool], limit: float = 60.0,
           timeout: float = TIMEOUT) -> tuple[list[dict[str, Any]], str, int]:
    """Poll the three devices as fast as possible until ``until(records)`` (or ``limit``
    seconds: a hang guard), then SIGINT. Returns the records, stderr and the exit status."""
    # (the simulator answers at any speed: 115200 baud, the line's silences are shorter)
    p = PollProcess("--port", port, "--baudrate", "115200", "--interval", "0", "--timeout",
                    str(timeout), *(f"huiwen-aq@{u}" for u in UNITS))
    p.until(until, limit)
    stderr, code = p.stop()
    return p.records, stderr, code


def ok_counts(records: list[dict[str, Any]]) -> Counter[int]:
    return Counter(r["address"] for r in records if r["field"] == "co2" and r["status"] == "ok")


def enough(faulty_attempts: int) -> Callable[[list[dict[str, Any]]], bool]:
    """Stop once each live device has 8 good scans and the faulty one had its attempts."""
    def done(records: list[dict[str, Any]]) -> bool:
        ok = ok_counts(records)
        tried = sum(1 for r in records if r["address"] == FAULTY and r["field"] == "co2")
        return all(ok[u] >= 8 for u in UNITS if u != FAULTY) and tried >= faulty_attempts
    return done


def assert_no_misattribution(records: list[dict[str, Any]]) -> None:
    """Every value read belongs to the device it is reported for; no stale failed values."""
    for r in records:
        if r["status"] == "ok":
            expected = pinned(r["address"]).get(r["field"])
            if expected is not None:
                assert r["value"] == expected, f"{r['device']} {r['field']}: {r['value']}"
        else:
            assert r["value"] is None and r["raw"] is None and r["error"], r


# fault on device 2 -> (its spec, cycles of it to wait for, the statuses its readings must
# show, exactly). Timeout 0.25 s, one retry; "@2-5": the device's requests 2 to 5 only.
FAULTS: dict[str, tuple[str, int, set[str]]] = {
    "dead": ("2:dead", 2, {"timeout", "skipped"}),
    # answers after both tries gave up: the late replies arrive while the bus drains
    "slow": ("2:slow=0.8", 2, {"timeout", "skipped"}),
    # the second block's answer is late twice (a timeout); the device had already answered
    # in that cycle, so the rest of it is still read
    "slow-once": ("2:slow=0.8@5-6", 2, {"ok", "timeout"}),
    # late once: the retry's prompt answer is taken, the late one is drained
    "late-then-retried": ("2:slow=0.35@2", 1, {"ok"}),
    "crc": ("2:crc@2-5", 1, {"ok", "garbled"}),
    "truncated": ("2:truncate@2-5", 1, {"ok", "garbled"}),
    "stray-byte": ("2:stray=0xFF", 1, {"ok"}),
    "wrong-id": ("2:wrong-id=3", 2, {"timeout", "skipped"}),
    "wrong-id-first": ("2:wrong-id-first=3", 1, {"ok"}),
    "exception": ("2:exception=4", 1, {"exception"}),
    "lose-first": ("2:lose-first=2", 2, {"timeout", "skipped", "ok"}),
}


def virtual_stream(spec: str, until: Callable[[list[dict[str, Any]]], bool],
                   limit: float = 600.0) -> tuple[list[dict[str, Any]], float]:
    """What ``stream`` does, in virtual time: the scheduler polls the three devices as fast
    as possible on the one virtual bus (tests/virtual.py: the simulator's engine and the
    line's rules) until ``until(records)`` or ``limit`` virtual seconds. The records as
    ``poll --format json`` writes them, and the virtual seconds it took."""
    bus, clock = simulated([f"huiwen-aq@{u}" for u in UNITS], [spec])
    for u in UNITS:
        for name, value in pinned(u).items():
            bus.engine.device(u).pin(name, value)
    site = from_specs("virtual", [("huiwen-aq", u) for u in UNITS], interval=0,
                      timeout=TIMEOUT, check_serial=False)
    bp = BusPoller(site.buses[0], bus, backoff=Backoff(), clock=clock, wall=clock)
    records: list[dict[str, Any]] = []
    start = clock.now

    async def go() -> None:
        while not until(records) and clock.now - start < limit:
            dev = bp.next_device()
            clock.now = max(clock.now, dev.next_due)
            await bp.run_one(dev, lambda d, rs: records.extend(
                json.loads(json.dumps(reading_record(r))) for r in rs))

    asyncio.run(go())
    return records, clock.now - start


@pytest.mark.parametrize("kind", sorted(FAULTS))
def test_in_virtual_time_live_devices_keep_flowing_and_the_faulty_one_is_reported(
        kind: str) -> None:
    """Every fault kind through the real scheduler and line rules, in milliseconds."""
    spec, cycles, statuses = FAULTS[kind]
    records, took = virtual_stream(spec, enough(cycles))
    assert enough(cycles)(records), (took, ok_counts(records))
    assert_no_misattribution(records)
    mine = Counter(r["status"] for r in records if r["address"] == FAULTY)
    assert set(mine) == statuses, mine
    if kind == "exception":
        errors = {r["error"] for r in records if r["address"] == FAULTY}
        assert errors == {"device 2 answered to function 0x04 with exception 04 SERVER DEVICE "
                          "FAILURE"}


# one end-to-end run of the real command per family of faults: no answer, a garbled
# answer, another unit's answer, an exception (every kind is run above in virtual time)
END_TO_END = ["dead", "crc", "wrong-id", "exception"]


@pytest.mark.parametrize("kind", END_TO_END)
def test_live_devices_keep_flowing_and_the_faulty_one_is_reported(
        kind: str, sim: Callable[..., SimulatedBus]) -> None:
    spec, _, statuses = FAULTS[kind]
    bus = start_bus(sim, spec)
    # one cycle of the faulty device: its next ones come after its backoff (a dead one's
    # second chance is a second of waiting), a rule about time shown above in virtual time;
    # a faulty device that answers (never "timeout") is not asked within a short timeout
    records, stderr, code = stream(bus.port, until=enough(1),
                                   timeout=TIMEOUT if "timeout" in statuses else ANSWERED)

    assert code == 0 and stderr == ""
    assert_no_misattribution(records)
    ok = ok_counts(records)
    assert ok[1] >= 8 and ok[3] >= 8, ok  # the live devices were read all along
    mine = Counter(r["status"] for r in records if r["address"] == FAULTY)
    assert set(mine) == statuses, mine
    if kind == "exception":
        errors = {r["error"] for r in records if r["address"] == FAULTY}
        assert errors == {"device 2 answered to function 0x04 with exception 04 SERVER DEVICE "
                          "FAILURE"}


def test_sigterm_also_ends_a_stream_cleanly(sim: Callable[..., SimulatedBus]) -> None:
    bus = start_bus(sim)
    cmd = [sys.executable, "-m", "rtupoll", "poll", "--port", bus.port, "--interval", "0",
           "--format", "csv", *(f"huiwen-aq@{u}" for u in UNITS)]
    proc = rtupoll_popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    header = proc.stdout.readline()
    first = proc.stdout.readline()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and err == ""
    assert header.startswith("time,device,profile,address,field,value,unit,raw,")
    assert first.count(",") >= header.count(",")
    assert out == "" or out.endswith("\n")


def test_an_unplugged_adapter_is_reported_and_polling_resumes_when_it_is_back(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    link = tmp_path / "ttyUSB0"
    first = sim("huiwen-aq@1", link=str(link))
    p = PollProcess("--port", str(link), "--interval", "0.05", "--timeout", str(TIMEOUT),
                    "--fields", "co2", "huiwen-aq@1")

    def oks(records: list[dict[str, Any]]) -> int:
        return sum(r["status"] == "ok" for r in records)

    assert p.until(lambda rs: oks(rs) >= 3, 60)  # (hang guards: each ends when it is so)
    first.stop()  # the adapter is pulled out
    assert p.until(lambda rs: rs[-1]["status"] == "port", 60)
    before = oks(p.records)
    sim("huiwen-aq@1", link=str(link))  # ... and plugged in again
    assert p.until(lambda rs: oks(rs) >= before + 3, 60)
    stderr, code = p.stop()
    assert code == 0 and stderr == ""
    gone = [r for r in p.records if r["status"] == "port"]
    assert gone and all(r["value"] is None and r["error"] for r in gone)
