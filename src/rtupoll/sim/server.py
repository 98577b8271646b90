"""Serving a simulated bus: a pseudo-terminal or RTU-over-TCP, with wire timing.

A pty looks to a client exactly like a USB/RS-485 adapter: mbpoll, pymodbus or rtupoll
open its slave path as a serial port. The simulator keeps the slave side open itself, so
a client can close and reopen the port (as a one-shot ``rtupoll read`` does) without the
master side seeing a hang-up. ``--tcp`` serves the same bytes over TCP, the way a serial
gateway forwards RTU frames.

Wire timing (``baudrate``): a pty delivers a request in one piece at once, so the server
acts as if it had been on the wire: the reply goes out when a real device's would be
complete -- request bytes at that baud, the 3.5-character silence that ends a frame, the
device's turnaround, then the reply's own bytes. Without a baud rate replies go out at
once (plus a turnaround explicitly configured for a device).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from rtupoll.errors import PortError, UsageError
from rtupoll.io import clock as line_clock
from rtupoll.io.pty_parity import pty_parity_of
from rtupoll.rtu import FUNCTION_NAMES, Framing
from rtupoll.sim.engine import Deframer, Engine, Transmission

T = TypeVar("T")
QUIET = 0.1  # seconds without bytes after which an unfinished frame is garbage
# frames kept in the wire log: a window of the latest, so a simulator left running for days
# holds the same memory as after its first minute (every frame ever seen is counted in
# Engine.requests/replies; --verbose prints them all as they pass)
WIRE_LOG = 1000
TIMER_SLACK = 0.0015  # asyncio timers fire up to 1 ms late; the rest is slept exactly
# pseudo-terminals are POSIX's (Linux, macOS); Windows has none: there a simulated line is
# served over TCP only (``serve_tcp``), and asking for a pty is one line (``NO_PTY``)
PTYS = hasattr(os, "openpty")
NO_PTY = ("a simulated serial port is a pseudo-terminal, which only POSIX systems (Linux, "
          "macOS) have: on Windows serve it over TCP (--tcp 127.0.0.1:5020) and give "
          "rtupoll --port tcp://127.0.0.1:5020")


@dataclass(frozen=True, slots=True)
class WireFrame:
    """Bytes seen on the simulated wire: ``in`` from the master, ``out`` from devices."""

    time: float  # the line's clock (rtupoll.io.clock), as every time on a bus
    direction: str  # "in" or "out" ("none": a request got no reply; only to on_wire)
    data: bytes
    note: str = ""  # what it is: a request summary, "garbage", or the faults applied

    def __str__(self) -> str:
        if self.direction == "none":
            return f"   ({self.note})"
        arrow = "->" if self.direction == "in" else "<-"
        return f"{arrow} {self.data.hex(' ').upper()}" + (f"  ({self.note})" if self.note else "")


def describe(frame: bytes) -> str:
    """A request in words, for the wire log: ``unit 1 read input 0x0006 x2``."""
    unit, fc = frame[0], frame[1]
    what = FUNCTION_NAMES.get(fc, f"function {fc}")
    if fc in (1, 2, 3, 4, 5, 6, 15, 16) and len(frame) >= 8:
        address, n = struct.unpack(">HH", frame[2:6])
        tail = f" x{n}" if fc in (1, 2, 3, 4, 15, 16) else f" = 0x{n:04X}"
        return f"unit {unit} {what} 0x{address:04X}{tail}"
    return f"unit {unit} {what}"


class _Link:
    """One connection to the master (the pty, or one TCP client) with its own receiver."""

    def __init__(self, server: Server, write: Callable[[bytes], None],
                 hang_up: Callable[[], None] | None = None) -> None:
        self.server, self.write, self.hang_up = server, write, hang_up
        self.deframer = Deframer()
        self.free_at = 0.0  # when the wire is free for the next reply
        self.last_byte = -math.inf  # when the last byte on the line ended (either way)
        self._idle = math.inf  # the silence before the frame being received began
        self._echo_at = 0.0  # when the last byte echoed (with wire timing) comes back
        self._flush: asyncio.TimerHandle | None = None
        self.closed = False

    def received(self, data: bytes, parity: str | None = None) -> None:
        """Bytes from the master; ``parity``: the one it sent them at (a pty's, as the
        master marked it), None where there is none (TCP)."""
        srv = self.server
        now = line_clock.now()
        if srv.echo and not self.closed:  # an adapter whose receiver is always on
            self._echo(data, now)
        ends = now + (srv.framing.wire_time(len(data)) if srv.framing else 0.0)
        srv.to_tap(data, ends)
        if not self.deframer.buffer:  # a frame may begin here: the silence before it
            self._idle = now - self.last_byte
        self.last_byte = max(self.last_byte, ends)
        for kind, chunk in self.deframer.feed(data):
            srv.log(now, "in", chunk, "garbage" if kind == "garbage" else describe(chunk))
            if kind == "frame":
                self._respond(chunk, now, self._idle, parity)
            self._idle = 0.0  # what follows in the same burst came back to back
        if self._flush:
            self._flush.cancel()
        self._flush = srv.loop.call_later(QUIET, self._quiet) if self.deframer.buffer else None

    def _echo(self, data: bytes, now: float) -> None:
        """Hand the master's bytes back as a 2-wire adapter does: with wire timing each
        byte as it leaves the wire (one character time after the one before, from the
        last one still going out); without, all at once."""
        srv, fr = self.server, self.server.framing
        if fr is None:
            self.write(data)
            return
        at = max(now, self._echo_at)
        for i in range(len(data)):
            at += fr.char_time
            srv.later(at, self._echo_byte, data[i : i + 1])
        self._echo_at = at

    def _echo_byte(self, byte: bytes) -> None:
        if not self.closed:
            with contextlib.suppress(OSError):  # nobody reading: lost, as on a wire
                self.write(byte)

    def _quiet(self) -> None:
        self._flush = None
        left = self.deframer.flush()
        if left:
            self.server.log(line_clock.now(), "in", left, "garbage")

    def _respond(self, frame: bytes, now: float, idle: float = math.inf,
                 parity: str | None = None) -> None:
        srv, fr = self.server, self.server.framing
        silence = fr.silence if fr else 0.0
        request_end = now + (fr.wire_time(len(frame)) if fr else 0.0)
        replies = srv.engine.handle(frame, now, idle, parity)
        if not replies and srv.on_wire:  # silence is not on the wire, but people ask why
            srv.on_wire(WireFrame(now, "none", b"", f"no reply: {srv.engine.why_silent}"))
        for tx in replies:
            turnaround = tx.turnaround if (fr or tx.explicit) else 0.0
            start = request_end + silence + turnaround
            if not tx.delay:
                start = max(start, self.free_at)
            end = start + (fr.wire_time(len(tx.data)) if fr else 0.0)
            if not tx.delay:  # a late reply collides on a real bus; it does not hold it
                self.free_at = end + silence
            if tx.pause:  # the first half, then the rest after the pause
                half = len(tx.data) // 2
                first = dataclasses.replace(tx, data=tx.data[:half])
                rest = dataclasses.replace(tx, data=tx.data[half:], notes=())
                srv.later(end + tx.delay, self._send, first)
                srv.later(end + tx.delay + tx.pause, self._send, rest)
                continue
            srv.later(end + tx.delay, self._send, tx)

    def _send(self, tx: Transmission) -> None:
        if self.closed:
            return
        srv = self.server
        now = line_clock.now()
        self.last_byte = max(self.last_byte, now)  # its last byte leaves the wire now
        # logged first: whoever reads the reply can already find it in the wire log
        srv.log(now, "out", tx.data, ", ".join(tx.notes))
        srv.to_tap(tx.data)
        try:
            self.write(tx.data)
        except OSError as exc:  # nobody reading and the pty buffer full: lost, as on a wire
            if srv.on_wire:
                srv.on_wire(WireFrame(now, "none", b"", f"reply lost: {exc.strerror}"))

    def close(self) -> None:
        self.closed = True
        if self._flush:
            self._flush.cancel()
        if self.hang_up:  # a TCP client sees end-of-file, as when a gateway goes away
            self.hang_up()


class Server:
    """Serves one Engine on a pty or TCP and keeps the wire log."""

    def __init__(self, engine: Engine, *, framing: Framing | None = None,
                 on_wire: Callable[[WireFrame], None] | None = None) -> None:
        self.engine, self.framing, self.on_wire = engine, framing, on_wire
        self.echo = False  # the master's adapter echoes what the master sends (its own bytes)
        self.loop = asyncio.get_running_loop()
        self.wire: collections.deque[WireFrame] = collections.deque(maxlen=WIRE_LOG)
        self.wire_lock = threading.Lock()  # tests read the log from another thread
        self.port = ""
        self._pending: set[asyncio.TimerHandle] = set()
        self._links: list[_Link] = []
        self._fds: list[int] = []
        self._link_path: Path | None = None
        self._tcp: asyncio.Server | None = None
        self._tap: int | None = None  # the tap pty's master: hears every byte on the line
        self._tap_link: Path | None = None

    def log(self, when: float, direction: str, data: bytes, note: str = "") -> None:
        frame = WireFrame(when, direction, data, note)
        with self.wire_lock:
            self.wire.append(frame)
        if self.on_wire:
            self.on_wire(frame)

    def later(self, when: float, fn: Callable[[T], None], tx: T) -> None:
        """Run ``fn(tx)`` at ``when``, to well under a millisecond.

        asyncio rounds its selector timeouts up to whole milliseconds, which at 115200
        baud is a third of a transaction; so wake a little early and sleep the rest.
        """
        box: list[asyncio.TimerHandle] = []  # not the handle itself: no reference cycle

        def run() -> None:
            self._pending.discard(box.pop())
            rest = when - line_clock.now()
            if rest > 0:
                time.sleep(rest)
            fn(tx)

        box.append(self.loop.call_later(when - TIMER_SLACK - line_clock.now(), run))
        self._pending.add(box[0])

    # -- transports ---------------------------------------------------------
    async def serve_pty(self, link: str | None = None) -> str:
        """Open a pseudo-terminal; returns the path a client opens (or the link to it)."""
        if not PTYS:
            raise UsageError(NO_PTY)
        import tty  # (POSIX only, as ptys are)

        master, slave = os.openpty()
        self._fds += [master, slave]
        tty.setraw(slave)  # no echo, no line editing: bytes pass as they are
        os.set_blocking(master, False)
        path = os.ttyname(slave)
        pty_link = _Link(self, lambda data: _write_all(master, data))
        self._links.append(pty_link)

        def readable() -> None:
            try:
                data = os.read(master, 4096)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # EIO cannot happen while we hold the slave open; be safe anyway
            if not data:
                return
            mismatch = self._line_mismatch(slave)
            if mismatch:  # a real device sees framing errors at the wrong speed: silence
                self.log(line_clock.now(), "in", data, f"garbage: {mismatch}")
                return
            pty_link.received(data, pty_parity_of(slave))

        self.loop.add_reader(master, readable)
        if link:
            self._link_path = _make_link(Path(link), path)
        self.port = path
        return path

    async def serve_tap(self, link: str) -> str:
        """A second pty that receives a copy of every byte on the line (for a sniffer);
        ``link`` becomes a symbolic link to it. Bytes written to it are ignored."""
        if not PTYS:
            raise UsageError(f"--tap: {NO_PTY}")
        import tty

        master, slave = os.openpty()
        self._fds += [master, slave]
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._tap = master
        path = os.ttyname(slave)
        self._tap_link = _make_link(Path(link), path)
        return path

    def to_tap(self, data: bytes, at: float | None = None) -> None:
        """Copy bytes on the line to the tap: now, or at ``at`` (when they end on the wire)."""
        if self._tap is None:
            return
        if at is not None and at > line_clock.now():
            box: list[asyncio.TimerHandle] = []

            def copy() -> None:
                self._pending.discard(box.pop())
                self.to_tap(data)

            box.append(self.loop.call_later(at - line_clock.now(), copy))
            self._pending.add(box[0])
            return
        with contextlib.suppress(OSError):  # nobody listening, the pty buffer full: lost
            _write_all(self._tap, data)

    def _line_mismatch(self, fd: int) -> str | None:
        """With wire timing, why the client's line settings would garble this bus, if they do.

        A pty carries bytes at any speed, but pyserial still sets the speed it was asked
        for on the tty; comparing it lets 'rtupoll scan' find a device at its own baud rate
        and nowhere else, as on a real wire. (Parity is each device's to hear: a pty has
        no parity bit, but a master marks the parity it set, ``pty_parity.pty_parity``,
        and ``Engine.handle`` lets only the devices at that parity hear the request.)
        """
        if not self.framing:
            return None
        import termios  # (a pty's: POSIX only)

        ospeed = termios.tcgetattr(fd)[5]
        want = self.framing.baudrate
        if ospeed != getattr(termios, f"B{want}", ospeed):
            return f"sent at another baud rate than the bus's {want}"
        return None

    async def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> str:
        """Listen for RTU-over-TCP clients; returns ``tcp://HOST:PORT``."""
        server = self

        class Protocol(asyncio.Protocol):
            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                assert isinstance(transport, asyncio.Transport)
                self.link = _Link(server, transport.write, transport.close)
                server._links.append(self.link)

            def data_received(self, data: bytes) -> None:
                self.link.received(data)

            def connection_lost(self, exc: Exception | None) -> None:
                self.link.close()
                if self.link in server._links:
                    server._links.remove(self.link)

        try:
            self._tcp = await self.loop.create_server(Protocol, host, port)
        except OSError as exc:
            raise PortError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        bound = self._tcp.sockets[0].getsockname()
        self.port = f"tcp://{host}:{bound[1]}"
        return self.port

    async def close(self) -> None:
        for handle in self._pending:
            handle.cancel()
        self._pending.clear()
        for link in list(self._links):
            link.close()
        if self._tcp is not None:
            self._tcp.close()
            await self._tcp.wait_closed()
        for fd in self._fds:
            self.loop.remove_reader(fd)  # only the master has one; others: a no-op
            os.close(fd)
        self._fds.clear()
        if self._link_path is not None and self._link_path.is_symlink():
            self._link_path.unlink()
        if self._tap_link is not None and self._tap_link.is_symlink():
            self._tap_link.unlink()
        self._tap = None


def _write_all(fd: int, data: bytes) -> None:
    while data:
        n = os.write(fd, data)
        data = data[n:]


def _make_link(link: Path, target: str) -> Path:
    if link.is_symlink():
        link.unlink()
    elif link.exists():
        raise UsageError(f"--link {link}: exists and is not a symbolic link; not replacing it")
    try:
        link.symlink_to(target)
    except OSError as exc:
        raise UsageError(f"--link {link}: {exc.strerror}") from None
    return link
