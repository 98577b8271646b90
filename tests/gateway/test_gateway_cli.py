"""End to end: the real ``rtupoll poll --serve`` as a subprocess, mbpoll (``-m tcp``) and
raw RTU-over-TCP sockets as the other masters, the simulator as the line."""

from __future__ import annotations

import json
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import pytest
from conftest import ANSWERED
from forked_cli import rtupoll_popen
from pipe_fill import stall

from rtupoll.rtu import crc_ok, with_crc
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port

Sim = Callable[..., SimulatedBus]
MBPOLL = shutil.which("mbpoll")
ANSWERED_S = f"{ANSWERED:g}"  # (as mbpoll's -o and rtupoll's options take it)


@dataclass
class Served:
    """``rtupoll poll --serve``'s process and port; once stopped, its stdout, stderr and
    status."""

    proc: subprocess.Popen[str]
    port: int
    out: str = ""
    err: str = ""
    returncode: int | None = None


@contextmanager
def rtupoll(*args: str) -> Iterator[Served]:
    """``rtupoll poll ... --serve 127.0.0.1:PORT``, until it listens; stopped by SIGTERM,
    its output read as it ends (a reader of its stdout, as a pipeline has)."""
    port = free_port()
    serve = next((a for a in args if a.startswith("rtu+tcp://")), None)
    listen = serve.replace("PORT", str(port)) if serve else f"127.0.0.1:{port}"
    argv = [a for a in args if a != serve]
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", *argv, "--serve", listen],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    served = Served(proc, port)
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                socket.create_connection(("127.0.0.1", served.port), timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"rtupoll did not listen: {proc.communicate()}"
                                         ) from None
                time.sleep(0.05)
        yield served
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        served.out, served.err = proc.communicate(timeout=60)
        served.returncode = proc.returncode


def mbpoll(port: int, *args: str, write: tuple[str, ...] = ()
           ) -> subprocess.CompletedProcess[str]:
    assert MBPOLL is not None
    return subprocess.run([MBPOLL, "-m", "tcp", "-p", str(port), "-1", "-o", ANSWERED_S, *args,
                           "127.0.0.1", *write], capture_output=True, text=True, timeout=60)


def values(out: str) -> list[int]:
    return [int(line.split()[-1]) for line in out.splitlines() if line.startswith("[")]


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (scripts/test installs it)")
def test_mbpoll_reads_and_writes_through_rtupoll_polling_the_same_line(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "net-irnet-pro@1", tick=None)
    bus.set(3, "co2", 640)
    with rtupoll("--port", bus.port, "--baudrate", "9600", "--interval", "0", "--timeout",
                 ANSWERED_S, "--format", "json", "huiwen-aq@3", "net-irnet-pro@1") as served:
        port = served.port
        read = mbpoll(port, "-a", "3", "-t", "3", "-r", "30007", "-c", "4")  # 0x7536..
        wrote = mbpoll(port, "-a", "1", "-t", "4:hex", "-r", "513",
                       write=("0x0000", "0x4248"))
        back = mbpoll(port, "-a", "1", "-t", "4", "-r", "513", "-c", "2")
        silent = mbpoll(port, "-a", "9", "-t", "4", "-r", "1")  # 0x0B after --serve-timeout
        time.sleep(0.3)
    assert read.returncode == 0, read.stdout + read.stderr
    assert values(read.stdout) == list(bus.registers(3, "input", 0x7536, 4))
    assert values(read.stdout)[3] == 640
    assert wrote.returncode == 0, wrote.stdout + wrote.stderr
    assert values(back.stdout) == [0, 0x4248]
    assert silent.returncode != 0 and "Target device failed to respond" in silent.stderr
    recs = [json.loads(line) for line in served.out.splitlines()]
    assert len(recs) > 40 and {r["status"] for r in recs} == {"ok"}  # polling kept going
    assert not [w for w in bus.wire if w.direction == "in" and "garbage" in w.note]
    assert served.returncode == 0, served.err


def test_a_pure_gateway_serves_rtu_over_tcp(sim: Sim) -> None:
    bus = sim("radar-level@4", tick=None)
    bus.set(4, "air_gap_cm", 321)
    with rtupoll("--port", bus.port, "--serve-timeout", ANSWERED_S,
                 "rtu+tcp://127.0.0.1:PORT") as served, \
            socket.create_connection(("127.0.0.1", served.port), timeout=30) as s:  # (hang
        # guards: the reply, and the close, end the waits)
        s.sendall(with_crc(bytes.fromhex("04 03 00 00 00 01")))
        reply = b""
        while len(reply) < 7:
            reply += s.recv(64)
        s.sendall(with_crc(bytes.fromhex("04 03 00 00 00 01"))[:-1] + b"\x00")  # bad CRC
        end = s.recv(64)
    assert crc_ok(reply) and reply[:5] == bytes.fromhex("04 03 02 01 41")  # 321
    assert end == b"" and "CRC error" in served.err and served.returncode == 0


def test_a_stdout_nobody_reads_stops_neither_the_gateway_nor_sigterm(sim: Sim) -> None:
    """``poll --serve ... | consumer`` whose consumer stalls: the records wait in their
    writer's thread (ui.pipe_writer), so a Modbus TCP client is still answered once the
    pipe is full, and SIGTERM still ends the run, saying what was not written."""
    bus = sim("huiwen-aq@3", "net-irnet-pro@1", tick=None)
    bus.set(3, "co2", 640)
    port = free_port()
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "--port", bus.port,
                          "--baudrate", "9600", "--interval", "0", "--format", "json",
                          "huiwen-aq@3", "net-irnet-pro@1", "--serve", f"127.0.0.1:{port}"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    try:
        stall(proc, bus)  # nobody reads: the pipe fills, then the queue
        with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
            s.sendall(bytes.fromhex("00 07 00 00 00 06 03 04 75 39 00 01"))  # co2
            reply = b""
            while len(reply) < 11:
                reply += s.recv(64) or b"-" * 11
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert reply == bytes.fromhex("00 07 00 00 00 05 03 04 02 02 80")  # 640
    out, err = proc.stdout.read(), proc.stderr.read().decode()
    assert out.endswith(b"\n") and all(json.loads(line) for line in out.splitlines())
    assert "bytes of records not written: nothing read them for 2 s" in err

