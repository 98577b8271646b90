"""``rtupoll simulate`` as a user runs it: a process that serves until it is told to stop."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_runner import rtupoll
from conftest import ANSWERED, RawPort
from forked_cli import rtupoll_popen
from pipe_fill import wait_full

from rtupoll.rtu.messages import ReadReply, ReadRequest

Raw = Callable[[str], RawPort]


class Simulator:
    """A running ``rtupoll simulate`` process and what it printed so far."""

    def __init__(self, *args: str) -> None:
        self.proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "simulate", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.seen = ""
        self.out = self.until("Press Ctrl-C to stop.")
        found = re.search(r" on ([^\s,]+)", self.out)
        assert found, self.out
        self.port = found.group(1)

    def until(self, text: str, timeout: float = 60) -> str:
        """Output up to and including ``text`` (raw reads: no buffer hides what arrived)."""
        assert self.proc.stdout is not None
        fd, deadline = self.proc.stdout.fileno(), time.monotonic() + timeout
        while text not in self.seen:
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            chunk = os.read(fd, 4096).decode() if ready else ""
            if not chunk:
                raise AssertionError(f"no {text!r} in output:\n{self.seen}{self.stop()}")
            self.seen += chunk
        end = self.seen.index(text) + len(text)
        out, self.seen = self.seen[:end], self.seen[end:]
        return out

    def stop(self, sig: int = signal.SIGINT) -> str:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=10)
        return self.seen + out.decode() + err.decode()


@pytest.fixture
def simulate() -> Iterator[Callable[..., Simulator]]:
    started: list[Simulator] = []

    def start(*args: str) -> Simulator:
        started.append(Simulator(*args))
        return started[-1]

    yield start
    for s in started:
        if s.proc.poll() is None:
            s.proc.kill()
            s.proc.communicate()


def test_default_bus_lists_its_devices_serves_and_stops_on_ctrl_c(
        simulate: Callable[..., Simulator], raw_port: Raw) -> None:
    s = simulate("--tick", "0")
    for pid in ("net-irnet-pro", "radar-level", "huiwen-aq", "co2meter-an117", "banner-ez-array"):
        assert pid in s.out
    assert "also answers 254 = 0xFE" in s.out
    # a bus that could exist: four devices at 9600, the CO2Meter board alone at 115200
    assert f"rtupoll read -p {s.port} -b 9600 net-irnet-pro@1" in s.out
    assert "line 2 (a serial port: open it at 115200 baud)" in s.out
    port = raw_port(s.port, 9600)
    assert port.transact(ReadRequest(3, 3, 40001, 1).frame(), 7) == \
        ReadReply(3, 3, (3,)).frame()
    rest = s.stop(signal.SIGINT)
    assert s.proc.returncode == 0
    assert "stopped after 1 requests (1 replies)." in rest
    assert "Traceback" not in rest


def test_sigterm_stops_cleanly_and_removes_the_link(simulate: Callable[..., Simulator],
                                                    tmp_path: Path) -> None:
    link = tmp_path / "ttyRTU"
    s = simulate("huiwen-aq@3", "--link", str(link))
    assert os.readlink(link) == s.port and f", linked as {link} " in s.out
    rest = s.stop(signal.SIGTERM)
    assert s.proc.returncode == 0 and "stopped" in rest and "Traceback" not in rest
    assert not link.is_symlink()


def test_mbpoll_reads_a_value_pinned_on_the_command_line(simulate: Callable[..., Simulator]
                                                         ) -> None:
    s = simulate("huiwen-aq@3", "--set", "huiwen-aq@3.co2=812", "--baud", "9600")
    assert "Wire timing: 9600 baud" in s.out
    run = subprocess.run(["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-0", "-1",
                          "-o", f"{ANSWERED:g}",  # (the reply ends its wait: not mbpoll's 1 s)
                          "-a", "3", "-t", "3", "-r", "30009", s.port],
                         capture_output=True, text=True, timeout=60, check=False)
    assert re.search(r"\[30009\]:\s+812$", run.stdout, re.MULTILINE), run.stdout
    s.stop()


def test_verbose_prints_the_frames_and_faults(simulate: Callable[..., Simulator],
                                              raw_port: Raw) -> None:
    s = simulate("net-irnet-pro@1", "-v", "--fault", "1:crc@2", "--tick", "0")
    port = raw_port(s.port, 4800)
    read = ReadRequest(1, 4, 6, 2).frame()
    port.transact(read, 9)
    port.transact(read, 9)
    out = s.until("(crc)")
    assert "-> 01 04 00 06 00 02 91 CA  (unit 1 read input registers 0x0006 x2)" in out
    s.stop()


def test_verbose_to_a_pipe_nobody_reads_holds_no_reply_back(
        simulate: Callable[..., Simulator], raw_port: Raw) -> None:
    """The frames queue beyond the full pipe (ui.pipe_writer): the devices go on
    answering, Ctrl-C ends it, and what was never read is counted on stderr."""
    s = simulate("net-irnet-pro@1", "-v", "--tick", "0")
    port = raw_port(s.port, 4800)
    read = ReadRequest(1, 4, 6, 2).frame()
    assert s.proc.stdout is not None

    def more() -> None:  # traffic: frames for the full pipe
        for _ in range(40):
            assert len(port.transact(read, 9)) == 9
    wait_full(s.proc.stdout.fileno(), more)  # nothing reads: the pipe is full
    for _ in range(200):  # (the simulator's thread once blocked in its write here)
        assert len(port.transact(read, 9)) == 9
    s.proc.send_signal(signal.SIGINT)
    assert s.proc.wait(timeout=60) == 0  # (still unread: its stdout)
    assert s.proc.stderr is not None
    err = s.proc.stderr.read()
    assert re.search(rb"^rtupoll: stdout: \d+ bytes not written: nothing read them for 2 s$",
                     err, re.MULTILINE), err
    assert b"Traceback" not in err


def test_tcp(simulate: Callable[..., Simulator], raw_port: Raw) -> None:
    s = simulate("huiwen-aq@3", "--tcp", "127.0.0.1:0")
    assert s.port.startswith("tcp://127.0.0.1:")
    assert raw_port(s.port).transact(ReadRequest(3, 3, 40001, 1).frame(), 7) == \
        ReadReply(3, 3, (3,)).frame()
    s.stop()


@pytest.mark.parametrize(("args", "message"), [
    (["nope@1"], "rtupoll: no profile 'nope'"),
    (["huiwen-aq@3", "--fault", "3:deadd"], "unknown kind 'deadd' (did you mean 'dead'?)"),
    (["huiwen-aq@3", "--set", "huiwen-aq@3.co2=x"], "rtupoll: co2: 'x' is not a number"),
    (["--tcp", "127.0.0.1:0", "--link", "/tmp/x"], "cannot be used with --tcp"),
])
def test_mistakes_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    run = rtupoll("simulate", *args)  # in this process: refused before it serves
    assert run.returncode == 2
    assert message in run.stderr and len(run.stderr.strip().splitlines()) == 1, run.stderr
