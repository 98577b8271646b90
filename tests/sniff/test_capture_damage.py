"""Captures that end badly: a truncated or damaged pcapng is read up to the damage (as
Wireshark does) and says where it stopped; an enhanced packet block too short to hold
its header is damage, not a ``struct.error``, for ``sniff --read`` and ``simulate
--replay``; ``sniff --capture`` on a full disk (a file size limit here) stops only the
capture, with whole blocks kept and one line said, and goes on listening; a port that
hangs up (an adapter unplugged) ends ``sniff`` in one line, with what it heard kept."""

from __future__ import annotations

import os
import resource
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import rtupoll
from conftest import ANSWERED

from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.sim.replay import load_replay
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sniff.capfile import CaptureWriter, read_capture

# a child under a file-size limit must not write Python's bytecode cache: the interpreter
# renames a .pyc cut short by the limit into place, and every later rtupoll start that
# imports that module then fails (EOFError)
NO_BYTECODE = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}

Sim = Callable[..., SimulatedBus]
RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))
REQ = ReadRequest(3, 4, 0x7536, 2).frame()
REPLY = ReadReply(3, 4, (25, 50)).frame()


def capture(path: Path, n: int = 6) -> list[int]:
    """A capture of ``n`` packets (requests and replies); the byte offset where the first
    packet block starts, then the offset after each."""
    w = CaptureWriter(path, Framing(9600), "/dev/ttyUSB0")
    for i in range(n):
        w.write(REQ if i % 2 == 0 else REPLY, 1_700_000_000 + i * 0.05)
    w.close()
    raw = path.read_bytes()
    ends, i = [], 0
    while i < len(raw):
        i += struct.unpack("<I", raw[i + 4 : i + 8])[0]
        ends.append(i)
    return ends[1:]  # from the end of the interface block


def test_a_capture_cut_anywhere_reads_every_whole_packet_before_the_cut(tmp_path: Path
                                                                         ) -> None:
    whole = tmp_path / "whole.pcapng"
    first, *ends = capture(whole)
    raw = whole.read_bytes()
    for cut in range(first + 1, len(raw)):
        path = tmp_path / "cut.pcapng"
        path.write_bytes(raw[:cut])
        got = read_capture(path)
        packets = sum(1 for e in ends if e <= cut)
        assert len(got.chunks) == packets, cut
        assert [d for _, d in got.chunks] == [REQ, REPLY, REQ, REPLY, REQ, REPLY][:packets]
        assert (got.stopped == "") == (cut in ends)
        if got.stopped:
            assert f"at byte {max([first, *(e for e in ends if e <= cut)])}" in got.stopped
            assert f"read the {packets} packets before it" in got.stopped


def test_a_zero_filled_tail_after_a_power_loss_stops_there(tmp_path: Path) -> None:
    path = tmp_path / "cap.pcapng"
    ends = capture(path, 4)[1:]
    path.write_bytes(path.read_bytes() + b"\0" * 4096)  # blocks the file system allocated
    got = read_capture(path)
    assert len(got.chunks) == 4 and f"at byte {ends[-1]}" in got.stopped


def short_block(path: Path) -> int:
    """A capture whose third packet block says it is 12 bytes long (header only)."""
    ends = capture(path, 4)[1:]
    raw = path.read_bytes()
    bad = struct.pack("<II", 6, 12) + struct.pack("<I", 12)
    path.write_bytes(raw[: ends[1]] + bad + raw[ends[1]:])
    return ends[1]


def test_a_short_enhanced_packet_block_ends_sniff_read_there_in_one_line(tmp_path: Path
                                                                          ) -> None:
    path = tmp_path / "short.pcapng"
    at = short_block(path)
    done = rtupoll("sniff", "--read", str(path), "--format", "frames")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and "struct.error" not in done.stderr
    assert done.stderr.strip() == (f"rtupoll: {path}: an enhanced packet block of 12 bytes "
                                   f"(at least 32) at byte {at}: read the 2 packets before it")
    assert len(done.stdout.splitlines()) == 1  # the one request and its reply


def test_a_short_enhanced_packet_block_replays_what_came_before(tmp_path: Path) -> None:
    path = tmp_path / "short.pcapng"
    short_block(path)
    engine, line = load_replay(path)
    assert line == Framing(9600)
    assert [t.data for t in engine.handle(REQ)] == [REPLY]  # the packets before the damage


def limited(size: int) -> Callable[[], None]:
    def apply() -> None:  # in the child: files it writes stop growing at ``size`` bytes
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
    return apply


@pytest.mark.skipif(sys.platform != "linux", reason="RLIMIT_FSIZE as a full disk")
def test_sniff_capture_on_a_full_disk_stops_the_capture_and_listens_on(
        sim: Sim, tmp_path: Path) -> None:
    tap, path = str(tmp_path / "tap"), tmp_path / "line.pcapng"
    bus = sim("huiwen-aq@3", tick=None, tap=tap)
    proc = subprocess.Popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", "--format", "frames",
                             "--capture", str(path), "huiwen-aq@3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=NO_BYTECODE, preexec_fn=limited(1500))
    assert proc.stderr is not None
    assert "listening on" in proc.stderr.readline()
    poller = subprocess.Popen(["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-a", "3",
                               "-t", "3", "-r", "30007", "-c", "2", "-l", "20", "-o", "0.5",
                               bus.port], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while sum(1 for w in bus.wire if w.direction == "in") < 40:
            assert time.monotonic() < deadline and poller.poll() is None
            time.sleep(0.05)
    finally:
        poller.terminate()
        poller.wait(timeout=10)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    said = [x for x in err.splitlines() if "stopped" in x]
    assert len(said) == 1 and said[0].startswith(f"rtupoll: capture to {path} stopped: "), err
    assert len(out.splitlines()) >= 15  # listening went on after the capture stopped
    back = read_capture(path)
    assert back.stopped == ""  # whole blocks only
    kept = int(said[0].split("its first ")[1].split()[0])
    assert len(back.chunks) == kept > 0 and path.stat().st_size <= 1500


def test_sniff_on_a_port_that_hangs_up_says_so_in_one_line_and_keeps_what_it_heard(
        sim: Sim, tmp_path: Path) -> None:
    """The tap's pty closed under it, as an unplugged adapter's port: the port's exit
    code and one line, the transaction heard printed and captured (it once read the dead
    port's nothing in a loop, at a core's full speed, until killed)."""
    tap, path = str(tmp_path / "tap"), tmp_path / "line.pcapng"
    bus = sim("huiwen-aq@3", tick=None, tap=tap)
    proc = subprocess.Popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", "--format", "frames",
                             "--capture", str(path), "huiwen-aq@3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stderr is not None
    try:
        assert "listening on" in proc.stderr.readline()
        subprocess.run(["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-a", "3", "-t", "3",
                        "-r", "30007", "-c", "2", "-1", "-o", str(ANSWERED), bus.port],
                       stdout=subprocess.DEVNULL, check=True, timeout=ANSWERED * 2)
        heard = proc.stdout.readline()  # (the transaction, read by sniff before the end)
        bus.stop()
        rest, err = proc.communicate(timeout=ANSWERED)
    finally:
        proc.kill()
    assert "huiwen-aq@3  fc04 read input 0x7536 x2" in heard and "pm25=" in heard, heard
    assert proc.returncode == 3 and rest == "", err
    assert err.splitlines() == [f"rtupoll: {tap}: the port hung up (adapter unplugged?)"], err
    kept = b"".join(data for _, data in read_capture(path).chunks)
    assert kept[:8] == REQ and kept[8:11] == b"\x03\x04\x04" and len(kept) == 17  # both
