"""``rtupoll simulate --replay``: a capture's devices answer as they did on site."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from forked_cli import rtupoll_popen

from rtupoll.errors import UsageError
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest
from rtupoll.sim.replay import load_replay
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sniff.capfile import CaptureWriter

Sim = Callable[..., SimulatedBus]
RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))
F = Framing(9600)
CO2 = ReadRequest(3, 4, 30009, 1).frame()
BLOCK = ReadRequest(3, 4, 30006, 4).frame()


def write_capture(path: Path, exchanges: list[tuple[bytes, bytes | None, float]]) -> None:
    """Request, reply (None: no answer) and reply time, one exchange every 100 ms."""
    w = CaptureWriter(path, F, "/dev/ttyUSB0")
    t = 1_700_000_000.0
    for request, reply, delay in exchanges:
        end = t + F.wire_time(len(request))
        w.write(request, end)
        if reply is not None:
            w.write(reply, end + delay + F.wire_time(len(reply)))
        t += 0.1
    w.close()


def mbpoll(port: str, address: int, count: int, unit: int = 3, timeout: float = 10) -> str:
    """mbpoll's output; ``timeout``: its own, for a reply that comes all the time a busy
    machine may need (the reply ends the wait), short for one that must not come."""
    run = subprocess.run(["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-0", "-1",
                          "-o", f"{timeout:g}", "-a", str(unit), "-t", "3", "-r", str(address),
                          "-c", str(count), port], capture_output=True, text=True, timeout=60,
                         check=False)
    return run.stdout + run.stderr


def values(out: str) -> list[int]:
    return [int(v) for v in re.findall(r"^\[\d+\]:\s+(-?\d+)", out, re.MULTILINE)]


def test_the_engine_answers_each_request_as_captured_in_order(tmp_path: Path) -> None:
    path = tmp_path / "cap.pcapng"
    write_capture(path, [(CO2, ReadReply(3, 4, (650,)).frame(), 0.030),
                         (CO2, None, 0.0),
                         (CO2, ReadReply(3, 4, (700,)).frame(), 0.045),
                         (BLOCK, ReadReply(3, 4, (25, 50, 250, 700)).frame(), 0.020)])
    engine, line = load_replay(path)
    assert line.baudrate == 9600
    first = engine.handle(CO2)
    assert [t.data for t in first] == [ReadReply(3, 4, (650,)).frame()]
    assert first[0].turnaround == pytest.approx(0.030, abs=2e-3) and first[0].explicit
    assert engine.handle(CO2) == []  # it did not answer the second time
    assert [t.data for t in engine.handle(CO2)] == [ReadReply(3, 4, (700,)).frame()]
    assert [t.data for t in engine.handle(CO2)] == [ReadReply(3, 4, (650,)).frame()]  # cycles
    # not captured as such, but every register is known: the latest values
    part = ReadRequest(3, 4, 30007, 2).frame()
    assert [t.data for t in engine.handle(part)] == [ReadReply(3, 4, (50, 250)).frame()]
    unknown = ReadRequest(3, 4, 40, 1).frame()
    assert [t.data for t in engine.handle(unknown)] == [ExceptionReply(3, 4, 2).frame()]
    assert engine.handle(ReadRequest(9, 4, 1, 1).frame()) == []  # no such unit


def test_a_capture_without_requests_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "empty.pcapng"
    write_capture(path, [])
    with pytest.raises(UsageError, match="no request"):
        load_replay(path)


def test_a_replayed_capture_answers_mbpoll_with_the_captured_values(tmp_path: Path) -> None:
    path = tmp_path / "cap.pcapng"
    write_capture(path, [(CO2, ReadReply(3, 4, (650,)).frame(), 0.02),
                         (BLOCK, ReadReply(3, 4, (25, 50, 250, 650)).frame(), 0.02),
                         (ReadRequest(3, 4, 30100, 1).frame(), ExceptionReply(3, 4, 2).frame(),
                          0.02)])
    proc = subprocess.Popen([RTUPOLL, "simulate", "--replay", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        head = proc.stdout.readline()
        found = re.search(r" on (/dev/pts/\d+)", head)
        assert found, head + proc.stderr.read() if proc.stderr else head
        port = found.group(1)
        assert values(mbpoll(port, 30009, 1)) == [650]
        assert values(mbpoll(port, 30006, 4)) == [25, 50, 250, 650]
        assert "Illegal data address" in mbpoll(port, 30100, 1)
        assert "timed out" in mbpoll(port, 30009, 1, unit=4, timeout=0.3)  # not captured
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "stopped after 4 requests (3 replies)" in out


def stop(proc: subprocess.Popen[str]) -> str:
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    return out


def reply_times(frames: str) -> list[float]:
    return [float(ms) for ms in re.findall(r"reply (\d+\.\d) ms", frames)]


def test_a_live_capture_replays_its_values_and_reply_times(sim: Sim, tmp_path: Path) -> None:
    """Sniff mbpoll reading a timed simulator, replay the capture: mbpoll reading the
    replay gets the same values, each after at least the reply time captured on site."""
    tap, path = str(tmp_path / "tap"), tmp_path / "site.pcapng"
    bus = sim("huiwen-aq@3", tick=None, baudrate=9600, tap=tap,
              sets=["huiwen-aq@3.co2=777", "huiwen-aq@3.pm25=42"],
              options=["huiwen-aq@3.turnaround=0.08"])  # far above a read's own time
    sniffer = rtupoll_popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", "--format",
                                "frames", "--capture", str(path)], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    assert sniffer.stderr is not None and "listening on" in sniffer.stderr.readline()
    site = [values(mbpoll(bus.port, 30009, 1)), values(mbpoll(bus.port, 30006, 4))]
    captured = reply_times(stop(sniffer))
    bus.stop()
    assert site == [[777], [42, *bus.registers(3, "input", 30007, 3)]]
    assert len(captured) == 2

    proc = rtupoll_popen([RTUPOLL, "simulate", "--replay", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        found = re.search(r" on (/dev/pts/\d+)", proc.stdout.readline())
        assert found
        replayed, took = [], []
        for address, count in ((30009, 1), (30006, 4)):
            began = time.monotonic()
            replayed.append(values(mbpoll(found.group(1), address, count)))
            took.append((time.monotonic() - began) * 1000)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=10)
    assert replayed == site
    # the replay waits each captured reply time before it answers, so mbpoll (start,
    # request, reply) takes longer; a busy machine only lengthens that. The engine's own
    # test holds the reply times themselves (test_the_engine_answers_each_request...)
    assert all(t > c for t, c in zip(took, captured, strict=True)), (captured, took)
