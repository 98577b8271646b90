"""One bus's gateway: an asyncio listener, a worker per client, requests onto the line.

Each connection has a reader (bytes -> frames through the sans-IO decoder) and a
worker that answers its frames in order. Before a request may take a turn on the
line (``turns``) it is checked (``pdu.parse``, ``access``); a request for a device
the scheduler has backed off as offline is answered 0x0B at once, a read the cache
covers from the cache. Waiting for the line, each client's first request has a place
of its own and further ones share ``queue`` places (``turns.Places``); one more is
answered 0x0A at once.

Back-pressure: a client has at most ``client_queue`` requests in hand (waiting, on the
line, or answered and being written). Its worker waits while more than ``HIGH_WATER``
bytes of its replies are unread (beyond its receive buffer and ``SEND_BUFFER``), so a
client that does not read its replies soon has its ``client_queue`` in hand, and then
nothing more is read from it: its requests
stay in the kernel's buffers and its own, not in rtupoll's memory or the shared queue.

A client that disconnects with a request on the line does not cut it short (a
transaction abandoned half-way would leave its reply to collide with the next
request): it completes, its reply is dropped. Its requests not yet on the line are
dropped unsent, with one log line: at once when its end of the stream is read, and
otherwise when one gets its turn and the socket shows the client gone (a hang-up
behind requests not read yet). A frame that cannot be trusted (``MbapError``) closes
that client's connection with one log line; nothing of it reaches the line.
Connections beyond ``max_clients`` (or ``max_per_address`` from one address) are
closed as they come, counted and logged once per interval.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import select
import socket
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any

from rtupoll.backoff import after_failures
from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.errors import DeviceTimeout, FrameError, PortError, RefusedError
from rtupoll.gateway import mbap, rtutcp
from rtupoll.gateway.access import Access
from rtupoll.gateway.cache import ReadCache
from rtupoll.gateway.clients import ClientStats
from rtupoll.gateway.pdu import (
    Ask,
    BadRequest,
    parse,
)
from rtupoll.gateway.turns import Places, Turns
from rtupoll.jobs.stats import State
from rtupoll.refusals import Refusals, watch
from rtupoll.rtu.effects import Effect, effect, writes
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.messages import ExceptionReply, ReadReply

if TYPE_CHECKING:
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller
    from rtupoll.jobs.stats import Reading

Log = Callable[[str], None]
Clock = Callable[[], float]
KEEP_CLIENTS = 32  # disconnected clients' counters kept for the footer and JSON
EVENTS = 5  # log lines kept for the live table
STOP_WAIT = 2.0  # seconds a stopping gateway lets a request on the line complete
# A client that does not read its replies is found out once they fill its receive
# buffer, the system's send buffer for it and asyncio's: these keep the last two small
# (a Modbus reply is at most 260 bytes; a client that reads has a few in flight at most)
HIGH_WATER = 2048  # bytes of a client's replies in asyncio's buffer before its worker waits
SEND_BUFFER = 4096  # the socket's send buffer (SO_SNDBUF; Linux doubles it, 4608 at least)
READ_LIMIT = 8 * 1024  # bytes read ahead from a client (asyncio pauses reading beyond 2x)
HANGUP = getattr(select, "POLLRDHUP", 0) | getattr(select, "POLLHUP", 0) | \
    getattr(select, "POLLERR", 0)


class SilentUnits:
    """Backoff for units rtupoll does not poll (a polled one has the scheduler's): after
    ``after`` timeouts in a row a unit is answered 0x0B at once for ``base`` seconds,
    doubling up to ``cap`` while each probe (the first request after the hold) also
    times out; one answer ends it. Pure: the caller gives the time."""

    def __init__(self, *, after: int = 3, base: float = 1.0, cap: float = 30.0) -> None:
        self.after, self.base, self.cap = after, base, cap
        self._failures: dict[int, int] = {}
        self._until: dict[int, float] = {}

    def held(self, unit: int, now: float) -> bool:
        return now < self._until.get(unit, 0.0)

    def timed_out(self, unit: int, now: float) -> None:
        n = self._failures[unit] = self._failures.get(unit, 0) + 1
        if n >= self.after:
            self._until[unit] = now + after_failures(n - self.after + 1, first=self.base,
                                                     cap=self.cap)

    def answered(self, unit: int) -> None:
        self._failures.pop(unit, None)
        self._until.pop(unit, None)


RULES = ("allow", "read_only", "cache", "broadcast", "setup_writes", "queue", "timeout",
         "client_queue", "max_clients", "max_per_address")


class _Lines(logging.Logger):
    """``Refusals``' log, as the gateway's own lines: its log (stderr) and the events
    under its line in the live table."""

    def __init__(self, gateway: Gateway) -> None:
        super().__init__("rtupoll.gateway")
        self._gateway = gateway

    def warning(self, msg: object, *args: object, **kwargs: Any) -> None:
        self._gateway.say(str(msg) % args)


class ClientGone(Exception):
    """A request's client has gone before its turn: it is dropped unsent."""


@dataclasses.dataclass(eq=False)
class Connection:
    """One client's requests in hand: waiting in ``queue``, on the line, or answered and
    being written (``in_hand`` counts them all)."""

    writer: asyncio.StreamWriter
    stats: ClientStats
    queue: asyncio.Queue[tuple[mbap.Frame, float, bytes | None] | None] = \
        dataclasses.field(default_factory=asyncio.Queue)
    room: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)
    in_hand: int = 0
    on_line: bool = False  # its request is on the line now (it completes)
    left: bool = False  # its end of the stream was read (or it must go)
    dropped: int = 0  # requests dropped unsent, because the client had gone
    dropped_writes: int = 0  # of those, writes

    def gone(self) -> bool:
        """Whether the client has gone: its end read, or the socket hung up (a hang-up
        shows behind requests not read yet, where reading would not find it)."""
        if self.left or self.writer.is_closing():
            return True
        sock = self.writer.get_extra_info("socket")
        if sock is None or not HANGUP or not hasattr(select, "poll"):
            return False
        poll = select.poll()
        poll.register(sock.fileno(), HANGUP)
        return bool(poll.poll(0))

    def drop(self, frame: mbap.Frame) -> None:
        self.dropped += 1
        if effect(frame.pdu) is Effect.WRITE:
            self.dropped_writes += 1


def _text(value: object) -> str:
    if isinstance(value, (tuple, frozenset)):
        return "[" + ", ".join(map(str, sorted(value, key=str))) + "]"
    return str(value).lower() if isinstance(value, bool) else str(value)


async def listen(config: ServeConfig, handle: Callable[[asyncio.StreamReader,
                 asyncio.StreamWriter], Awaitable[None]]) -> asyncio.Server:
    """A listener on ``config``'s address. ``[::]`` (or ``::``) listens dual-stack: IPv4
    clients too, as ``0.0.0.0`` would (the system's default for a v6 socket varies)."""
    try:
        if config.host in ("::", "[::]"):
            sock = socket.socket(socket.AF_INET6, socket.SOCK_STREAM)
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
                sock.bind(("::", config.port))
            except BaseException:
                sock.close()
                raise
            return await asyncio.start_server(handle, sock=sock, limit=READ_LIMIT)
        return await asyncio.start_server(handle, config.host, config.port, limit=READ_LIMIT)
    except OSError as exc:
        raise PortError(f"cannot serve {config.url}: {exc.strerror or exc}") from None


class Gateway:
    """Serves ``config`` for the bus ``poller`` polls, through the poller's transport."""

    def __init__(self, config: ServeConfig, poller: BusPoller, turns: Turns, *,
                 log: Log | None = None, info: Log | None = None,
                 clock: Clock = time.monotonic) -> None:
        self.config, self.poller, self.turns = config, poller, turns
        self.asked = config  # as configured (``config`` has the port a :0 was given)
        self.units: dict[int, DevicePoller]
        self.access: Access
        self._learn_devices()
        self.cache = ReadCache(config.cache) if config.cache > 0 else None
        self.silent = SilentUnits()  # units not polled that stopped answering
        self.clients: list[ClientStats] = []
        self.events: deque[str] = deque(maxlen=EVENTS)
        self.pending = 0  # requests queued or on the line, all clients
        self.places = Places(config.queue)
        # connections closed as they came (over max_clients or max_per_address) and
        # accepts that failed (EMFILE ...): counted, one log line a minute at most
        self.refusals = Refusals(f"gateway {config.url}", _Lines(self), clock=clock)
        self._unwatch: Callable[[], None] | None = None
        self._by_address: Counter[str] = Counter()  # connections open, by client address
        self._log, self._info, self._clock = log, info, clock
        self._server: asyncio.Server | None = None
        self._handlers: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()

    def _learn_devices(self) -> None:
        """The polled devices by unit, and the access rules for their profiles (again
        after a reload: ``reconfigure``)."""
        self.units = {d.config.address: d for d in self.poller.devices}
        self.access = Access(self.config, {u: d.config.profile for u, d in self.units.items()})

    # -- life ---------------------------------------------------------------------
    async def start(self, server: asyncio.Server | None = None) -> None:
        """Listen (or take ``server``, bound for it by ``listen``)."""
        self.asked = self.config  # as configured (port 0: the system chooses)
        self._server = server or await listen(self.config, self._handle)
        if self.config.port == 0:  # the port the system chose, in the log and the footer
            self.config = dataclasses.replace(self.config, port=self.address[1])
        self.refusals.what = f"gateway {self.config.url}"
        self._unwatch = watch(self._server.sockets, self.refusals)

    def reconfigure(self, config: ServeConfig) -> list[str]:
        """New rules on the same listener (a SIGHUP's ``serve:``): what changed. Clients
        the new ``allow:`` excludes are disconnected at once."""
        was, self.asked = self.asked, config
        self.config = dataclasses.replace(config, port=self.config.port)
        self._learn_devices()  # the devices the reload left, under the new rules
        if config.cache != was.cache:
            self.cache = ReadCache(config.cache) if config.cache > 0 else None
        self.places.shared = config.queue
        changed = [f"{k} {_text(getattr(was, k))} -> {_text(getattr(config, k))}"
                   for k in RULES if getattr(was, k) != getattr(config, k)]
        for writer in list(self._writers):
            peer = writer.get_extra_info("peername") or ("?", 0)
            if not self.access.peer_allowed(str(peer[0])):
                writer.close()
                changed.append(f"client {peer[0]} disconnected (not in the allowed networks)")
        return [f"serve {self.config.url}: " + "; ".join(changed)] if changed else []

    @property
    def address(self) -> tuple[str, int]:
        """Where it listens (the port the system chose, for ``:0``)."""
        assert self._server is not None and self._server.sockets
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    @property
    def refused_connections(self) -> int:
        return self.refusals.total

    async def stop(self) -> None:
        if self._unwatch is not None:  # (before the sockets close: their fds are reused)
            self._unwatch()
            self._unwatch = None
        self.refusals.flush()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None
        for writer in list(self._writers):  # each client sees the end of its stream
            writer.close()
        if self._handlers:
            await asyncio.wait(list(self._handlers), timeout=STOP_WAIT)
        for task in list(self._handlers):
            task.cancel()
        await asyncio.gather(*self._handlers, return_exceptions=True)

    def on_readings(self, dev: DevicePoller, readings: Sequence[Reading]) -> None:
        """The poller's decoded registers, for the cache."""
        if self.cache is None:
            return
        now = self._clock()
        for r in readings:
            if r.value is not None:
                self.cache.put(dev.config.address, r.field.table, r.field.address,
                               r.value.raw, now)

    def say(self, line: str) -> None:
        """A line of the gateway's own (``gateway URL: ...``): the log and the events."""
        self.events.append(line.split(": ", 1)[-1])
        if self._log is not None:
            self._log(line)

    def log(self, stats: ClientStats, message: str, *, once: str | None = None) -> None:
        """A log line about a client; with ``once``, only the first time for that reason."""
        if once is not None:
            if once in stats.logged:
                return
            stats.logged.add(once)
        self.events.append(f"client {stats.peer}: {message}")  # under the gateway's line
        line = f"gateway {self.config.url}: client {stats.peer}: {message}"
        if self._log is not None:
            self._log(line)

    # -- one connection -------------------------------------------------------------
    def _over_cap(self, host: str) -> str | None:
        """Why a new connection from ``host`` is refused (it is counted already), or None."""
        if len(self._writers) > self.config.max_clients:
            return f"over max_clients {self.config.max_clients}"
        if self._by_address[host] > self.config.max_per_address:
            return f"from {host} over max_per_address {self.config.max_per_address}"
        return None

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
                      ) -> None:
        task = asyncio.current_task()
        assert task is not None
        peer = writer.get_extra_info("peername") or ("?", 0)
        host = str(peer[0])
        self._handlers.add(task)
        self._writers.add(writer)
        self._by_address[host] += 1
        try:
            reason = self._over_cap(host)
            if reason is not None:
                self.refusals.refused(reason)
                writer.close()
                return
            await self._client(reader, writer, peer)
        finally:
            self._by_address[host] -= 1
            if not self._by_address[host]:
                del self._by_address[host]
            self._handlers.discard(task)
            self._writers.discard(writer)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                      peer: tuple[str, int]) -> None:
        stats = ClientStats(f"{peer[0]}:{peer[1]}" if ":" not in str(peer[0])
                            else f"[{peer[0]}]:{peer[1]}")
        self.clients.append(stats)
        del self.clients[:-KEEP_CLIENTS]
        try:
            if not self.access.peer_allowed(str(peer[0])):
                stats.refused += 1
                self.log(stats, "refused: not in the allowed networks "
                         f"({', '.join(map(str, self.config.allow))}); connection closed")
                return
            with contextlib.suppress(AttributeError, RuntimeError):
                writer.transport.set_write_buffer_limits(high=HIGH_WATER)
            sock = writer.get_extra_info("socket")
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
            await self._converse(reader, Connection(writer, stats))
        except asyncio.CancelledError:  # the gateway stops: the client is let go
            pass
        finally:
            stats.connected = False
            if stats.requests and self._info is not None:
                self._info(f"gateway {self.config.url}: client {stats.peer}: disconnected: "
                           f"{stats.summary()}")
            writer.close()
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await writer.wait_closed()

    async def _converse(self, reader: asyncio.StreamReader, conn: Connection) -> None:
        decoder = mbap.MbapDecoder() if self.config.framing == "mbap" else rtutcp.RtuDecoder()
        stats = conn.stats
        worker = asyncio.create_task(self._work(conn))
        try:
            while not worker.done() and not conn.left:
                try:
                    data = await reader.read(4096)
                except (ConnectionError, OSError):
                    break
                if not data:
                    break
                try:
                    frames = decoder.feed(data)
                except mbap.MbapError as exc:
                    self.log(stats, f"malformed frame, connection closed: {exc}")
                    break
                for frame in frames:
                    while conn.in_hand >= self.config.client_queue and not conn.left:
                        conn.room.clear()  # back-pressure: nothing more is read meanwhile
                        await conn.room.wait()
                    if conn.left:
                        conn.drop(frame)
                        continue
                    stats.requests += 1
                    conn.in_hand += 1
                    if not self.places.take(id(conn)):
                        stats.busy += 1
                        self.log(stats, f"queue full ({self.config.queue} requests): "
                                 "answered 0x0A", once="queue")
                        busy = ExceptionReply(frame.unit, frame.pdu[0],
                                              ExceptionCode.PATH_UNAVAILABLE)
                        conn.queue.put_nowait((frame, 0.0, busy.pdu()))
                        continue
                    self.pending += 1
                    conn.queue.put_nowait((frame, self._clock(), None))
        finally:
            conn.left = True
            self._drop_queued(conn)
            if not conn.on_line:  # waiting for its turn (or writing to a client gone)
                worker.cancel()
            conn.queue.put_nowait(None)
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.shield(worker)  # a request on the line completes
            stats.dropped += conn.dropped
            if conn.dropped:
                writes = f" ({conn.dropped_writes} write{'s' * (conn.dropped_writes != 1)})" \
                    if conn.dropped_writes else ""
                self.log(stats, f"gone before its turn: {conn.dropped} request"
                         f"{'s' * (conn.dropped != 1)} dropped unsent{writes}")

    def _drop_queued(self, conn: Connection) -> None:
        while not conn.queue.empty():  # not started: dropped with the connection
            item = conn.queue.get_nowait()
            if item is None:
                continue
            conn.in_hand -= 1
            if item[2] is None:  # it held a place
                self.pending -= 1
                self.places.give_back(id(conn))
                conn.drop(item[0])

    async def _work(self, conn: Connection) -> None:
        writer, stats = conn.writer, conn.stats
        while True:
            item = await conn.queue.get()
            if item is None:
                return
            frame, queued, reply = item
            try:
                if conn.left:  # gone: what is left is dropped unsent, or unanswered
                    if reply is None:
                        conn.drop(frame)
                        self.pending -= 1
                        self.places.give_back(id(conn))
                    continue
                if reply is None:
                    try:
                        reply = await self.answer(frame.unit, frame.pdu, stats, queued,
                                                  conn=conn)
                    except ClientGone:
                        conn.drop(frame)
                        conn.left = True  # the rest is dropped too, and reading ends
                        writer.close()
                        continue
                    except asyncio.CancelledError:
                        conn.drop(frame)
                        raise
                    finally:
                        self.pending -= 1
                        self.places.give_back(id(conn))
                if reply is not None and not writer.is_closing():
                    self._send(writer, frame, reply)
                    with contextlib.suppress(ConnectionError, OSError):
                        await writer.drain()  # waits while HIGH_WATER bytes are unread
            finally:
                conn.in_hand -= 1
                conn.room.set()

    def _send(self, writer: asyncio.StreamWriter, frame: mbap.Frame, pdu: bytes) -> None:
        if writer.is_closing():
            return
        data = rtutcp.encode(frame.unit, pdu) if frame.tid is None else \
            mbap.encode(frame.tid, frame.unit, pdu)
        with contextlib.suppress(ConnectionError, OSError, RuntimeError):
            writer.write(data)

    # -- one request ----------------------------------------------------------------
    async def answer(self, unit: int, pdu: bytes, stats: ClientStats,
                     queued: float | None = None, *, conn: Connection | None = None
                     ) -> bytes | None:
        """The reply PDU for one request (None: a broadcast, which has no reply).
        ``ClientGone`` when ``conn``'s client has gone as the request gets its turn."""
        try:
            ask = parse(pdu, unit=unit)
        except BadRequest as exc:
            stats.refused += 1
            self.log(stats, f"refused: {exc.reason}", once=exc.reason)
            return ExceptionReply(unit, pdu[0] if pdu else 0, exc.code).pdu()
        refusal = self.access.check(unit, ask)
        if refusal is not None:
            stats.refused += 1
            self.log(stats, f"refused: {refusal.reason}", once=refusal.reason)
            return ExceptionReply(unit, ask.function, refusal.code).pdu()
        dev = self.units.get(unit)
        if (dev is not None and dev.stats.state is State.OFFLINE) or \
                (dev is None and self.silent.held(unit, self._clock())):
            stats.timeouts += 1
            return ExceptionReply(unit, ask.function, ExceptionCode.TARGET_FAILED).pdu()
        if ask.read and self.cache is not None and ask.table is not None:
            got = self.cache.get(unit, ask.table, ask.address, ask.count, self._clock())
            if got is not None:
                stats.answered += 1
                stats.cached += 1
                return ReadReply(unit, ask.function, got).pdu()
        reply = await self._on_line(unit, ask, stats, queued, dev, conn)
        return None if unit == 0 else reply

    async def _on_line(self, unit: int, ask: Ask, stats: ClientStats, queued: float | None,
                       dev: DevicePoller | None, conn: Connection | None) -> bytes:
        timeout = dev.config.response_timeout if dev is not None else self.config.timeout
        if conn is not None and conn.gone():  # (no turn for a client already gone)
            raise ClientGone
        async with self.turns.turn(id(stats)):
            if conn is not None:
                if conn.gone():
                    raise ClientGone
                conn.on_line = True
            try:
                return await self._transact(unit, ask, stats, queued, dev, timeout)
            finally:
                if conn is not None:
                    conn.on_line = False

    async def _transact(self, unit: int, ask: Ask, stats: ClientStats, queued: float | None,
                        dev: DevicePoller | None, timeout: float) -> bytes:
        start = self._clock()
        if queued is not None:
            stats.waits.append(start - queued)
        failed = False
        try:
            reply = await self.poller.transport.transact(  # a polled device's idle gap too
                unit, ask.pdu, timeout=timeout, retries=0,
                idle_gap=None if dev is None else dev.config.gap)
            self.silent.answered(unit)
            if reply[:1] == bytes((ask.function | 0x80,)):
                stats.exceptions += 1
            else:
                stats.answered += 1
            return reply
        except (DeviceTimeout, FrameError) as exc:
            if isinstance(exc, DeviceTimeout) and dev is None and unit:
                self.silent.timed_out(unit, self._clock())
            failed = True
            stats.timeouts += 1
            return ExceptionReply(unit, ask.function, ExceptionCode.TARGET_FAILED).pdu()
        except RefusedError as exc:  # a function the bus cannot build
            stats.refused += 1
            self.log(stats, f"refused: {exc}", once=f"fc{ask.function}")
            return ExceptionReply(unit, ask.function, ExceptionCode.ILLEGAL_FUNCTION).pdu()
        except PortError as exc:
            stats.busy += 1
            self.log(stats, f"answered 0x0A: {exc}", once="port")
            return ExceptionReply(unit, ask.function, ExceptionCode.PATH_UNAVAILABLE).pdu()
        finally:
            end = self._clock()
            self.poller.load.add(end, end - start, failed=failed)
            if ask.write and self.cache is not None:  # FC 22 and 23 too
                for run in writes(ask.pdu) or ():
                    self.cache.forget(unit, run.table, run.address, run.count)
