"""``ui.pipe_writer``: records to a stdout pipe written by a thread, on real pipes. In
order and whole; a reader that lags holds the polling (the event) until it catches up;
one that never reads again costs ``close`` ``DRAIN`` seconds, leaves whole lines in the
pipe and the count of bytes not written; one that left raises on the next write."""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

import pytest
from pipe_fill import in_pipe

from rtupoll.ui import pipe_writer
from rtupoll.ui.pipe_writer import LIMIT, PIPE_BUF, RESUME, PipeWriter, _pieces, threaded

HANG = 60.0  # s: a hang guard, never a measure


@contextmanager
def pipe() -> Iterator[tuple[int, TextIO]]:
    """A pipe's read end and its write end as a text stream (what stdout is in a
    pipeline)."""
    r, w = os.pipe()
    stream = open(w, "w", encoding="utf-8")  # noqa: SIM115
    try:
        yield r, stream
    finally:
        stream.close()
        os.close(r)


def read_all(fd: int) -> bytes:
    out = b""
    while chunk := os.read(fd, 1 << 16):
        out += chunk
    return out


def test_batches_come_out_whole_and_in_order_after_what_was_printed_before() -> None:
    with pipe() as (r, stream):
        stream.write("before\n")  # buffered in the stream: written first
        writer = PipeWriter(stream)
        lines = [f'{{"n": {n}, "unit": "°C"}}\n' for n in range(2000)]
        for line in lines:
            assert writer.write(line) is None  # far below LIMIT while read
        reader = threading.Thread(target=lambda: got.append(read_all(r)))
        got: list[bytes] = []
        reader.start()
        assert writer.close() == 0
        stream.close()
        reader.join(HANG)
    assert got[0].decode() == "before\n" + "".join(lines)


def test_a_reader_that_lags_holds_the_polling_until_it_catches_up() -> None:
    line = "x" * 999 + "\n"

    async def main() -> tuple[int, bool, int]:
        with pipe() as (r, stream):
            writer = PipeWriter(stream)
            held = None
            written = 0
            while held is None:  # nobody reads: the pipe fills, then the queue
                held = writer.write(line)
                written += len(line)
            assert written >= LIMIT and not held.is_set()
            await asyncio.sleep(0.2)
            still_held = not held.is_set()  # nobody has read a byte meanwhile
            taken: list[bytes] = []
            reader = threading.Thread(target=lambda: taken.append(read_all(r)))
            reader.start()
            await asyncio.wait_for(held.wait(), HANG)  # set once the reader caught up
            left = writer.held
            assert writer.close() == 0
            stream.close()
            reader.join(HANG)
            assert len(taken[0]) == written  # nothing dropped
            return written, still_held, left

    written, still_held, left = asyncio.run(main())
    assert still_held and written >= LIMIT
    assert 0 <= left < RESUME


def test_a_reader_that_never_reads_again_leaves_whole_lines_and_a_count(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pipe_writer, "DRAIN", 0.2)
    with pipe() as (r, stream):
        writer = PipeWriter(stream)
        lines = [f"{n:06d}," + "y" * 300 + "\n" for n in range(400)]  # 122 KB: 2 pipes full
        for line in lines:
            writer.write(line)
        deadline = time.monotonic() + HANG
        while in_pipe(r) < 65536 - PIPE_BUF and time.monotonic() < deadline:
            time.sleep(0.01)  # the pipe fills
        left = writer.close()  # the thread is blocked in a write: given up on
        kept = os.read(r, 1 << 20)
    assert left > 0 and len(kept) + left == sum(map(len, lines))
    assert kept.endswith(b"\n")  # whole lines only: a pipe takes a piece whole or not
    assert kept.decode() == "".join(lines[: kept.count(b"\n")])


def test_a_reader_that_left_is_a_broken_pipe_on_the_next_write() -> None:
    r, w = os.pipe()
    stream = open(w, "w", encoding="utf-8")  # noqa: SIM115
    try:
        writer = PipeWriter(stream)
        os.close(r)
        deadline = time.monotonic() + HANG
        with pytest.raises(BrokenPipeError):
            while time.monotonic() < deadline:
                writer.write("a record\n")
                time.sleep(0.01)
        assert writer.close() == 0
    finally:
        stream.close()


def test_pieces_are_whole_lines_a_pipe_takes_whole() -> None:
    data = b"".join(b"z" * n + b"\n" for n in (100, 3000, 2000, PIPE_BUF + 7, 10))
    pieces = _pieces(data)
    assert b"".join(pieces) == data
    assert all(p.endswith(b"\n") for p in pieces)
    assert [len(p) for p in pieces] == [3102, 2001, PIPE_BUF + 8, 11]  # a long line alone
    assert _pieces(b"short\n") == [b"short\n"]


def test_only_a_pipe_or_a_socket_is_written_by_the_thread(tmp_path: Path) -> None:
    import io
    import socket

    with pipe() as (_, stream):
        assert threaded(stream)
    a, b = socket.socketpair()
    with a, b, open(a.fileno(), "w", encoding="utf-8", closefd=False) as sock:
        assert threaded(sock)
    assert not threaded(io.StringIO())  # no descriptor
    leader, follower = os.openpty()
    with open(follower, "w", encoding="utf-8") as tty:
        assert not threaded(tty)  # a terminal
    os.close(leader)
    with open(tmp_path / "records.jsonl", "w", encoding="utf-8") as file, \
            open(os.devnull, "w", encoding="utf-8") as null:
        assert not threaded(file) and not threaded(null)  # nothing at the other end
