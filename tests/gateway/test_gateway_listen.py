"""``--serve [::]:PORT`` listens dual-stack: the real ``rtupoll poll`` serving the
simulator, mbpoll over IPv4 and a raw socket over IPv6 as the clients."""

from __future__ import annotations

import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable

import pytest
from conftest import ANSWERED
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port

MBPOLL = shutil.which("mbpoll")


def ipv6() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


@pytest.mark.skipif(MBPOLL is None or not ipv6(), reason="needs mbpoll and IPv6 loopback")
def test_serve_on_the_ipv6_any_address_answers_ipv4_and_ipv6_clients(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    port = free_port()
    # (a device that answers: ANSWERED, rtupoll's and mbpoll's)
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "--port", bus.port,
                          "--baudrate", "9600", "--timeout", f"{ANSWERED:g}", "--format", "json",
                          "huiwen-aq@3", "--serve", f"[::]:{port}"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while True:
            try:
                socket.create_connection(("::1", port), timeout=1).close()
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, proc.stderr
                time.sleep(0.05)
        assert MBPOLL is not None
        v4 = subprocess.run([MBPOLL, "-m", "tcp", "-p", str(port), "-1", "-o", f"{ANSWERED:g}",
                             "-a", "3", "-t", "3", "-r", "30010", "127.0.0.1"],
                            capture_output=True, text=True, timeout=60)
        with socket.create_connection(("::1", port), timeout=30) as c:
            c.sendall(struct.pack(">HHHB", 7, 0, 6, 3) + bytes.fromhex("04 75 39 00 01"))
            v6 = c.recv(64)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    assert v4.returncode == 0, v4.stdout + v4.stderr
    co2 = bus.registers(3, "input", 0x7539, 1)[0]
    assert f"[30010]: \t{co2}" in v4.stdout or v4.stdout.split()[-1] == str(co2), v4.stdout
    assert v6[:2] == b"\x00\x07" and v6[7:9] == b"\x04\x02"  # the same read, answered
    assert int.from_bytes(v6[9:11], "big") == co2
