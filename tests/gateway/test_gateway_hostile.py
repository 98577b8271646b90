"""End to end, hostile gateway clients beside a normal one: the real ``rtupoll poll
--serve`` as a process of its own, the simulator on a pty as the line, clients on real
loopback sockets. A client that sends requests and never reads its replies (a receive
buffer as small as the system allows) gets no more than its share: the normal client's
replies keep coming, none of them 0x0A, and rtupoll's memory stays bounded. A client
that sends a write and leaves before its turn: the device never gets the write."""

from __future__ import annotations

import os
import resource
import select
import socket
import struct
import subprocess
import time
from collections.abc import Callable

from conftest import ANSWERED

from rtupoll.sim.runner import SimulatedBus
from tests.gateway.test_gateway_cli import rtupoll

Sim = Callable[..., SimulatedBus]
HANG = 60.0  # hang guards: what is waited for comes, or the test is broken


def rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def ask(s: socket.socket, tid: int, unit: int, pdu: bytes) -> bytes:
    """One request and its reply PDU, on a blocking socket."""
    s.sendall(mbap(tid, unit, pdu))
    got = b""
    while len(got) < 7 or len(got) < 6 + struct.unpack(">H", got[4:6])[0]:
        chunk = s.recv(512)
        assert chunk, "the gateway closed the normal client's connection"
        got += chunk
    assert struct.unpack(">H", got[:2])[0] == tid
    return got[7:]


def wait_for_line(proc: subprocess.Popen[str], text: str) -> str:
    """rtupoll's stderr up to the first line with ``text`` (read while it runs)."""
    assert proc.stderr is not None
    fd, seen, deadline = proc.stderr.fileno(), b"", time.monotonic() + HANG
    while text.encode() not in seen:
        assert time.monotonic() < deadline, f"no {text!r} in rtupoll's log: {seen!r}"
        if select.select([fd], [], [], 0.2)[0]:
            chunk = os.read(fd, 65536)
            assert chunk, f"rtupoll ended: {seen!r}"
            seen += chunk
    return seen.decode()


READ_CO2 = struct.pack(">BHH", 4, 0x7536, 4)  # huiwen-aq: PM2.5, TVOC, HCHO, CO2


def test_a_client_that_never_reads_takes_no_others_place_and_memory_stays_bounded(
        sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    with rtupoll("--port", bus.port, "--baudrate", "115200", "--interval", "0.5",
                 "--timeout", f"{ANSWERED:g}", "--format", "json", "huiwen-aq@3"
                 ) as served, socket.create_connection(("127.0.0.1", served.port), HANG) as s:
        proc, port = served.proc, served.port
        for tid in range(20):  # warm: the normal client's path has run before the baseline
            ask(s, tid, 3, READ_CO2)
        before = rss_kib(proc.pid)
        hog = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        hog.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)  # the system's least
        hog.connect(("127.0.0.1", port))
        hog.setblocking(False)
        sent, tid, stuck_since = 0, 0, None
        request = [mbap(t, 3, READ_CO2) for t in range(256)]
        replies: list[bytes] = []
        # the hog sends all it can (at most 40 MB, for at most 20 s, or until rtupoll has
        # not taken a byte of it for 2 s); the normal client asks between its sends
        start = time.monotonic()
        while sent < 40_000_000 and time.monotonic() - start < 20:
            batch = b"".join(request[(tid + i) % 256] for i in range(64))
            try:
                n = hog.send(batch)
                sent, tid, stuck_since = sent + n, tid + 64, None
            except BlockingIOError:
                stuck_since = stuck_since or time.monotonic()
                if time.monotonic() - stuck_since > 2:
                    break
                time.sleep(0.01)
            if len(replies) < 200 and tid % 1024 == 0:
                replies.append(ask(s, len(replies) % 65536, 3, READ_CO2))
        while len(replies) < 200:  # the hog still connected, never reading
            replies.append(ask(s, len(replies), 3, READ_CO2))
        after = rss_kib(proc.pid)
        hog.close()
    err = served.err
    assert {r[0] for r in replies} == {0x04}, sorted({r[:2].hex() for r in replies})
    # without back-pressure, rtupoll read all 40 MB and its 0x0A replies piled up unread
    assert sent < 20_000_000, sent
    assert after - before < 4 * 1024, (before, after, sent)  # kB (was +118 MB)
    assert served.returncode == 0, err


def test_a_write_from_a_client_that_left_before_its_turn_never_reaches_the_device(
        sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    was = list(bus.registers(1, "holding", 0x0200, 2))
    write = struct.pack(">BHHB", 16, 0x0200, 2, 4) + bytes.fromhex("0000 4248")
    with rtupoll("--port", bus.port, "--baudrate", "9600", "--interval", "1",
                 "--timeout", f"{ANSWERED:g}", "--serve-timeout", "5", "--format", "json",
                 "net-irnet-pro@1") as served:
        proc, port = served.proc, served.port
        holder = socket.create_connection(("127.0.0.1", port), HANG)
        holder.sendall(mbap(1, 9, struct.pack(">BHH", 3, 0, 1)))  # nobody at 9: 5 s
        wait_for_line_in_wire(bus, 9)
        with socket.create_connection(("127.0.0.1", port), HANG) as w:
            w.sendall(mbap(1, 1, write))  # waits behind unit 9's 5 s ...
        # ... and its client has left
        log = wait_for_line(proc, "dropped unsent")
        holder.settimeout(HANG)
        assert holder.recv(64)[7:] == bytes((0x83, 0x0B))  # unit 9's turn is over
        assert ask(holder, 2, 1, struct.pack(">BHH", 3, 0x0200, 2))[:2] == b"\x03\x04"
        holder.close()  # (the line has carried requests after the dropped one's place)
    err = served.err
    log += err
    assert "gone before its turn: 1 request dropped unsent (1 write)" in log, log
    assert list(bus.registers(1, "holding", 0x0200, 2)) == was
    assert not [f for f in bus.wire if f.direction == "in" and f.data[1:2] == b"\x10"]
    assert served.returncode == 0, err


def wait_for_line_in_wire(bus: SimulatedBus, unit: int) -> None:
    """Until the line has carried a request to ``unit``."""
    deadline = time.monotonic() + HANG
    while not [f for f in bus.wire if f.direction == "in" and f.data[:1] == bytes((unit,))]:
        assert time.monotonic() < deadline, "the request never reached the line"
        time.sleep(0.01)


def test_out_of_file_descriptors_it_says_so_once_and_serves_again_when_they_close(
        sim: Sim) -> None:
    """The process's limit lowered as a service manager's would be, the caps above it:
    idle connections take every descriptor; the accepts that fail meanwhile are counted
    in one line, never a traceback each; once they close, a client is served."""
    bus = sim("huiwen-aq@3", tick=None)
    limit = 64
    with rtupoll("--port", bus.port, "--baudrate", "9600", "--interval", "1",
                 "--timeout", f"{ANSWERED:g}", "--format", "json", "--serve-max-clients",
                 "5000", "--serve-max-per-address", "5000", "huiwen-aq@3") as served:
        proc, port = served.proc, served.port
        resource.prlimit(proc.pid, resource.RLIMIT_NOFILE, (limit, limit))
        used = len(os.listdir(f"/proc/{proc.pid}/fd"))
        idle = [socket.create_connection(("127.0.0.1", port), HANG)
                for _ in range(limit - used + 20)]  # more than it has descriptors left
        log = wait_for_line(proc, "out of file descriptors (EMFILE)")
        for s in idle:
            s.close()
        with socket.create_connection(("127.0.0.1", port), HANG) as s:
            s.settimeout(HANG)
            reply = ask(s, 1, 3, READ_CO2)
    err = served.err
    log += err
    assert reply[:2] == b"\x04\x08"
    assert "Traceback" not in log and "Too many open files" not in log, log[-2000:]
    lines = [x for x in log.splitlines() if f"{port}: refused" in x]
    assert 1 <= len(lines) <= 2, lines  # the first, and what was left at the stop
    assert "out of file descriptors (EMFILE) (counted from now on" in lines[0]
    assert served.returncode == 0, err
