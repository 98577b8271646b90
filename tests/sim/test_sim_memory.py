"""The simulator's memory is bounded (issue 32): what it keeps per request is counted,
its wire log is a window, and a replayed capture is streamed from its file.

Measured with tracemalloc on the real request path (a server's link receiving request
frames, the engine answering, replies going out through the event loop), in requests,
not in time: benchmarks/sim_memory.py measures the real commands for minutes.
"""

from __future__ import annotations

import asyncio
import gc
import sys
import tracemalloc
from pathlib import Path

import pytest

from rtupoll.model.planner import plan
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.engine import Engine
from rtupoll.sim.replay import AHEAD, load_replay
from rtupoll.sim.scenario import build
from rtupoll.sim.server import WIRE_LOG, Server, _Link
from rtupoll.sniff.capfile import CaptureWriter

DEVICES = ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "banner-ez-array@5"]


def requests(engine: Engine) -> list[bytes]:
    """The reads a poller of the engine's devices sends, one scan."""
    return [ReadRequest(d.address, b.table.read_function, b.address, b.count).frame()
            for d in engine.devices for b in plan(d.profile.default_fields(), d.profile)]


class Served:
    """A server with one link (a client's connection) answering request frames."""

    def __init__(self, engine: Engine) -> None:
        self.server = Server(engine, framing=None)
        self.replies = 0
        self.link = _Link(self.server, self._reply)

    def _reply(self, data: bytes) -> None:
        self.replies += 1

    async def serve(self, frames: list[bytes], n: int) -> int:
        """``n`` more requests, every reply sent; returns the memory traced after."""
        before = self.replies
        for i in range(n):
            self.link.received(frames[i % len(frames)])
            if i % 50 == 49:
                await asyncio.sleep(0)  # the replies go out
        while self.server._pending:
            await asyncio.sleep(0.001)
        assert self.replies - before == n  # every request was answered
        # the young generations only: a full collection empties the interpreter's free
        # lists, and what fills them (e.g. tuple(generator) parking one tuple per call in
        # the free list of its size, up to 2000 a size) is memory the process holds too
        gc.collect(1)
        return tracemalloc.get_traced_memory()[0]


def test_the_wire_log_is_a_window_of_the_latest_frames() -> None:
    engine = Engine(build(DEVICES).devices, tick=None)
    frames = requests(engine)

    async def run() -> Server:
        served = Served(engine)
        await served.serve(frames, WIRE_LOG)  # 2 frames each
        return served.server

    server = asyncio.run(run())
    assert len(server.wire) == WIRE_LOG
    last_in = [w.data for w in server.wire if w.direction == "in"][-1]
    assert last_in == frames[(WIRE_LOG - 1) % len(frames)]  # the newest are kept
    assert engine.requests == WIRE_LOG and engine.replies == WIRE_LOG  # counted, all


def test_serving_requests_does_not_grow_the_memory() -> None:
    engine = Engine(build(DEVICES).devices, tick=None)
    frames = requests(engine)

    async def run() -> tuple[int, int]:
        served = Served(engine)
        first = await served.serve(frames, WIRE_LOG)  # the window is full (2 frames each)
        second = await served.serve(frames, WIRE_LOG // 4)
        return first, second

    tracemalloc.start()
    try:
        first, second = asyncio.run(run())
    finally:
        tracemalloc.stop()
    # each request used to keep two frames (~430 bytes): 250 more requests, ~0.1 MB
    assert second - first < 50_000, (first, second)


def test_answering_reads_parks_no_tuples_in_the_interpreters_free_lists() -> None:
    # tuple(generator) starts from a 10-item tuple and shrinks it: every reply's register
    # tuple went to the free list of its own size when freed, up to 2000 a size (~0.9 MB
    # for these four devices, filled over 10+ minutes). Blocks in free lists are counted
    # by sys.getallocatedblocks() until a full collection, which a settled process rarely
    # makes; so measure without one.
    engine = Engine(build(DEVICES).devices, tick=None)
    frames = requests(engine)
    for i in range(200):
        engine.handle(frames[i % len(frames)])
    gc.collect()  # a clean start: the free lists empty
    before = sys.getallocatedblocks()
    for i in range(3000):
        assert engine.handle(frames[i % len(frames)])
    gc.collect(1)
    assert sys.getallocatedblocks() - before < 100, sys.getallocatedblocks() - before


def write_capture(path: Path, transactions: int) -> None:
    """The four devices polled in turn, answered by the simulator, at 115200 baud."""
    f = Framing(115200)
    engine = Engine(build(DEVICES).devices, tick=1.0)
    reads = requests(engine)
    w = CaptureWriter(path, f, "/dev/ttyUSB0")
    t = 1_700_000_000.0
    for i in range(transactions):
        request = reads[i % len(reads)]
        t += f.wire_time(len(request))
        w.write(request, t)
        for tx in engine.handle(request, t):
            t += f.silence + 0.005 + f.wire_time(len(tx.data))
            w.write(tx.data, t)
        t += 2 * f.silence
    w.close()


def replay_peak(path: Path, serve_requests: int) -> tuple[int, list[bytes]]:
    """Peak memory traced while loading a capture and answering requests from it."""
    tracemalloc.start()
    try:
        engine, _ = load_replay(path)
        reads = requests(Engine(build(DEVICES).devices, tick=None))
        answered = [tx.data for i in range(serve_requests)
                    for tx in engine.handle(reads[i % len(reads)])]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak, answered


@pytest.fixture(scope="module")
def captures(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Captures of 250 and 2000 transactions, by length."""
    where = tmp_path_factory.mktemp("captures")
    for transactions in (250, 2000):
        write_capture(where / f"{transactions}.pcapng", transactions)
    return {int(p.stem): p for p in where.iterdir()}


def test_a_replayed_capture_costs_the_same_memory_whatever_its_length(
        captures: dict[int, Path]) -> None:
    short, long = captures[250], captures[2000]
    assert long.stat().st_size > 7 * short.stat().st_size
    small, answers_short = replay_peak(short, 250)
    big, answers_long = replay_peak(long, 250)
    # loaded whole, the long one held 1750 answers more (a bytes object alone is 33
    # bytes and more, with its place in a list 41: 72 kB, above the allowance; the
    # capture's chunks held, 470 kB); bounded, the two peaks differ by 0-12 kB either way
    assert big - small < 50_000, (small, big)
    assert answers_short == answers_long  # the same start of the same story


def test_a_request_asked_alone_skips_ahead_within_a_bounded_queue(
        captures: dict[int, Path]) -> None:
    engine, _ = load_replay(captures[2000])
    reads = requests(Engine(build(DEVICES).devices, tick=None))
    for _ in range(300):  # only the first request: the others' answers are read past
        assert engine.handle(reads[0])
    waiting = [c.ahead for r, c in engine.captured.items() if r != reads[0]]
    assert waiting and all(q is not None and len(q) == AHEAD for q in waiting)
