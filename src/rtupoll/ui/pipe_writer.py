"""``poll``'s records, ``sniff``'s lines and ``simulate -v``'s frames on a stdout that
is a pipe (or a socket), written by a thread of their own: a reader that stops reading
never stops the event loop, the listening, nor the simulated devices.

Were the records written from the loop, a full pipe (``rtupoll poll ... | consumer``
whose consumer stalls) would block it in ``write``: the gateway's clients unanswered,
MQTT's keep-alive missed, and SIGTERM or Ctrl-C never handled, since the loop takes
them. Here each batch is queued whole and a thread writes it (``os.write`` on a
descriptor of its own, so ``sys.stdout``'s buffer is never held by a blocked thread),
in pieces of whole lines a pipe takes whole or not at all.
Once ``LIMIT`` bytes wait, ``write`` returns an event that holds the bus's polling until
the reader has caught up (``jobs.scheduler.Sink``): polling slows to the reader's pace,
nothing is dropped, and everything else (the gateway, MQTT's commands) goes on
(``sniff`` and ``simulate``, which cannot hold the line back, keep at most ``MOST``
bytes). At the end ``close`` waits for the queue to be written while the reader takes
something, and gives up after ``DRAIN`` seconds in which it took nothing, with the count
of bytes not written.

POSIX pipes and sockets only: on Windows (newline translation, console code pages), to
a file, a terminal or /dev/null the records are written directly.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import select
import stat
import threading
import time
from typing import TextIO

LIMIT = 1 << 20  # bytes queued before the buses wait for the reader
RESUME = LIMIT // 4  # bytes queued below which they go on
DRAIN = 2.0  # seconds ``close`` waits while the reader takes nothing
MOST = 64 << 20  # bytes queued at most by a writer that cannot hold its source back (sniff)
PIPE_BUF = getattr(select, "PIPE_BUF", 512)  # bytes a pipe takes in one write, or none


def unread(left: int, what: str = "bytes") -> str:
    """The line for the ``left`` bytes ``close`` could not write (``what``: as they are
    named)."""
    return f"stdout: {left} {what} not written: nothing read them for {DRAIN:g} s"


def threaded(stream: TextIO) -> bool:
    """Records to ``stream`` go through a ``PipeWriter``: on POSIX, a pipe or a socket
    (a reader at the other end; a file, a terminal or /dev/null takes what it is given)."""
    if os.name != "posix":
        return False
    try:
        mode = os.fstat(stream.fileno()).st_mode
    except (AttributeError, OSError, ValueError):  # (io.UnsupportedOperation is one)
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)


class PipeWriter:
    """Text for ``stream``, encoded as it encodes, written whole batches in order by a
    thread of its own. A write error (a reader gone: ``BrokenPipeError``) is raised by
    the next ``write``."""

    def __init__(self, stream: TextIO) -> None:
        stream.flush()  # what was printed before comes first
        self._fd = os.dup(stream.fileno())
        self._encoding, self._errors = stream.encoding, stream.errors or "strict"
        self._queue: collections.deque[bytes] = collections.deque()
        self._held = 0  # bytes queued or being written
        self._written = 0  # bytes written so far (progress, for ``close``)
        self._lock = threading.Condition()
        self._closing = False
        self._error: OSError | None = None
        self._room: asyncio.Event | None = None  # set while fewer than LIMIT bytes wait
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._run, name="rtupoll-records",
                                        daemon=True)  # (a reader that never reads: exit)
        self._thread.start()

    @property
    def held(self) -> int:
        """Bytes queued, not yet written."""
        return self._held

    def write(self, text: str) -> asyncio.Event | None:
        """Queue ``text``; with ``LIMIT`` bytes waiting, an event set once the reader has
        caught up (fewer than ``RESUME`` wait), else None."""
        if self._error is not None:
            raise type(self._error)(self._error.errno, self._error.strerror)
        data = text.encode(self._encoding, self._errors)
        with self._lock:
            self._queue.append(data)
            self._held += len(data)
            self._lock.notify_all()
            if self._held < LIMIT:
                return None
            try:
                self._loop = asyncio.get_running_loop()
            except RuntimeError:  # no loop: nothing to wait in
                return None
            if self._room is None:
                self._room = asyncio.Event()
            self._room.clear()
            return self._room

    def flush(self) -> None:
        """(Written as soon as the thread can: nothing to flush.)"""

    def close(self) -> int:
        """Wait while the reader takes what is queued; the bytes not written (a reader
        that took nothing for ``DRAIN`` s, or an error). The thread then ends."""
        with self._lock:
            self._closing = True
            self._lock.notify_all()
            mark, since = self._written, time.monotonic()
            while self._held and self._error is None:
                self._lock.wait(0.1)
                if self._written != mark:
                    mark, since = self._written, time.monotonic()
                elif time.monotonic() - since >= DRAIN:
                    break
            left = self._held if self._error is None else 0
        if not left:  # (else the thread may be in a write on it: left to the exit)
            self._thread.join()
            os.close(self._fd)
        return left

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._queue and not self._closing:
                    self._lock.wait()
                if not self._queue:
                    return
                data = self._queue[0]
            try:
                self._send(data)
            except OSError as exc:
                with self._lock:
                    self._error = exc
                    self._lock.notify_all()
                self._wake()
                return
            with self._lock:
                self._queue.popleft()
                self._held -= len(data)
                self._lock.notify_all()
                wake = self._held < RESUME
            if wake:
                self._wake()

    def _send(self, data: bytes) -> None:
        for piece in _pieces(data):
            view = memoryview(piece)
            while view:
                try:
                    n = os.write(self._fd, view)
                except BlockingIOError:  # a descriptor its opener made non-blocking
                    select.select([], [self._fd], [])
                    continue
                view = view[n:]
                with self._lock:
                    self._written += n
                    self._lock.notify_all()

    def _wake(self) -> None:
        """The buses waiting for room go on (from the thread, in the loop)."""
        loop, room = self._loop, self._room
        if loop is not None and room is not None and not room.is_set():
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(room.set)


def _pieces(data: bytes) -> list[bytes]:
    """``data`` in pieces of whole lines of at most ``PIPE_BUF`` bytes where it can be (a
    longer line alone): a pipe takes such a write whole or not at all, so one whose
    reader never reads again ends with a whole line."""
    if len(data) <= PIPE_BUF:
        return [data]
    out: list[bytes] = []
    start = 0
    while start < len(data):
        end = data.rfind(b"\n", start, start + PIPE_BUF) + 1
        if end <= start:  # a line longer than PIPE_BUF: to its end
            end = data.find(b"\n", start) + 1 or len(data)
        out.append(data[start:end])
        start = end
    return out
