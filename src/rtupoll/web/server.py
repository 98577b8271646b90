"""The dashboard's HTTP listener (aiohttp, the ``web`` extra): the page, its JSON, its events.

    GET /                 the page (static/index.html; every asset is in the package)
    GET /static/NAME      its script, style sheet and icon
    GET /api/state        the snapshot (``rtupoll.web.state``)
    GET /api/events       server-sent events: ``state`` first, then ``device`` per device
                          cycle (or MQTT state message), ``buses`` every few seconds
    GET /api/trend?device=KEY&field=NAME   the field's last hour: {"t": [...], "v": [...]}
    GET /metrics          Prometheus, when the source has it (``poll --http``)

Read-only: every other method is 405. Optional authentication (``HttpSettings``): a
bearer token (``Authorization: Bearer TOKEN``; a browser opens ``/?token=TOKEN`` once
and keeps a cookie) and/or users for basic authentication. On a loopback bind, a
request for another host name is 421 and one from another origin 403 (DNS rebinding).

Each connection goes through a ``Conn`` (the listener's ``Gate``): more than
``max_connections`` open at once are refused (503, closed), a request's headers must
all be in ``header_timeout`` seconds after its first byte, and a connection with no
request under way is closed after ``idle_timeout``. Refused connections and bad
requests (aiohttp's parser errors) are counted and logged once a minute
(``rtupoll.refusals``), never a traceback each.

An event stream never holds up polling: a reading only marks its device's event due;
every ``BATCH`` seconds the due events are made once (a device's event carries only
the fields whose reading changed, ``rtupoll.web.state``) and the same bytes go to every
stream, each written by its own task. A browser that stops reading gets a snapshot
when it reads again, never a backlog.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import hashlib
import hmac
import importlib.resources
import logging
import os
import sys
from collections import deque
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import urlsplit

from aiohttp import web

from rtupoll.errors import UsageError
from rtupoll.outputs.metrics_listener import LINGER, MAX_HEAD, REFUSED, TOO_LARGE, reset
from rtupoll.refusals import Refusals, watch
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.config.http_settings import HttpSettings

log = logging.getLogger("rtupoll.web")
PING = 15.0  # seconds between keep-alive events on the event streams
BATCH = 0.25  # seconds the events gather before they are written, the same to every stream
BEHIND = 4 << 20  # bytes a stream may fall behind before it is given a snapshot instead
BUDGET = 32 << 20  # bytes all streams may be behind together (the furthest behind drop)
CHUNK = 256 << 10  # bytes written to a stream at a time
CLOSE_WAIT = 0.5  # seconds open requests get to finish when the authentication changes
COOKIE = "rtupoll_token"
STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml",
                ".txt": "text/plain; charset=utf-8"}
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
                               "style-src 'self'; script-src 'self'; connect-src 'self'; "
                               "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY"}


class Client:
    """One event stream's bytes to write, in order; a client that falls ``BEHIND`` bytes
    behind (a browser that stopped reading) drops them and gets a fresh snapshot when it
    reads again, never a backlog. ``take`` hands out at most ``CHUNK`` bytes at a time
    (more when one event is larger), so what waits for a slow reader stays here,
    counted, not in its transport's buffer."""

    __slots__ = ("behind", "queue", "size", "wake")

    def __init__(self) -> None:
        self.queue: deque[bytes] = deque()
        self.size = 0
        self.behind = False
        self.wake = asyncio.Event()

    def put(self, data: bytes) -> None:
        if self.behind:
            return
        self.queue.append(data)
        self.size += len(data)
        if self.size > BEHIND:
            self.drop()
        self.wake.set()

    def drop(self) -> None:
        """Behind: what waits is dropped; a snapshot comes next."""
        self.queue.clear()
        self.size, self.behind = 0, True
        self.wake.set()

    def take(self) -> bytes:
        out: list[bytes] = []
        n = 0
        while self.queue and (not out or n + len(self.queue[0]) <= CHUNK):
            b = self.queue.popleft()
            out.append(b)
            n += len(b)
        self.size -= n
        if not self.queue:
            self.wake.clear()
        return b"".join(out)


def encode(event: str, data: str) -> bytes:
    return f"event: {event}\ndata: {data}\n\n".encode()


class Hub:
    """Every connected event stream. ``publish`` keeps the latest event of each key (a
    device, the buses) until the next flush, ``BATCH`` seconds after the first one; the
    flush makes each event's data (a function) once, when it is due, and gives the same
    bytes to every client. With nobody listening, ``publish`` does nothing.

    ``epoch`` counts the snapshots sent (a client that joined or fell behind): a device
    event made after a new snapshot carries every field, so deltas against the last
    flush never miss what changed between that flush and the snapshot."""

    def __init__(self) -> None:
        self.clients: set[Client] = set()
        self.pending: dict[str, tuple[str, str | Callable[[], str]]] = {}
        self.closed = False
        self.epoch = 0
        self._timer: asyncio.TimerHandle | None = None

    def publish(self, key: str, event: str, data: str | Callable[[], str]) -> None:
        if not self.clients or self.closed:
            return
        self.pending[key] = (event, data)
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(BATCH, self.flush)

    def flush(self) -> None:
        self._timer = None
        pending, self.pending = self.pending, {}
        if not self.clients or not pending:
            return
        out = b"".join(encode(event, data if isinstance(data, str) else data())
                       for event, data in pending.values())
        total = 0
        for c in self.clients:
            c.put(out)
            total += c.size
        if total > BUDGET:  # many slow readers: the furthest behind start afresh
            for c in sorted(self.clients, key=lambda c: c.size, reverse=True):
                total -= c.size
                c.drop()
                if total <= BUDGET:
                    break

    def join(self) -> Client:
        """A new client, before its snapshot is made (in the same step of the loop)."""
        c = Client()
        self.clients.add(c)
        self.epoch += 1
        return c

    def rejoin(self, client: Client) -> None:
        """A client that fell behind starts afresh, before its new snapshot is made."""
        client.queue.clear()
        client.size = 0
        client.wake.clear()
        client.behind = False
        self.epoch += 1

    def close(self) -> None:
        self.closed = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for c in self.clients:
            c.wake.set()


class Source(Protocol):
    """What the server shows: a polling process or a fleet seen through MQTT."""

    hub: Hub

    def snapshot(self) -> dict[str, Any]: ...

    def trend(self, key: str, field: str) -> dict[str, Any]: ...

    def metrics(self, accept: str) -> tuple[bytes, str] | None: ...


def load_assets() -> dict[str, tuple[bytes, str]]:
    """static/* from the package: name -> (bytes, content type)."""
    out: dict[str, tuple[bytes, str]] = {}
    root = importlib.resources.files("rtupoll.web") / "static"
    for entry in root.iterdir():
        ext = os.path.splitext(entry.name)[1]
        if ext in STATIC_TYPES:
            out[entry.name] = (entry.read_bytes(), STATIC_TYPES[ext])
    return out


def cookie_value(token: str) -> str:
    """What the cookie holds: a digest of the token, not the token itself."""
    return hashlib.sha256(f"rtupoll-web:{token}".encode()).hexdigest()


def _bytes(text: str) -> bytes:
    """A header's text as the bytes that came (aiohttp keeps undecodable bytes as
    surrogates): compared as bytes, never an error."""
    return text.encode("utf-8", "surrogateescape")


def authorised(settings: HttpSettings, headers: Any, cookies: Any, query: Any) -> bool:
    if not settings.guarded:
        return True
    auth = headers.get("Authorization", "")
    scheme, _, cred = auth.partition(" ")
    if settings.token:
        token = settings.token
        if scheme.lower() == "bearer" and hmac.compare_digest(_bytes(cred.strip()),
                                                              token.encode()):
            return True
        if hmac.compare_digest(_bytes(cookies.get(COOKIE, "")), cookie_value(token).encode()):
            return True
        if hmac.compare_digest(_bytes(query.get("token", "")), token.encode()):
            return True
    if settings.users and scheme.lower() == "basic":
        try:
            user, _, password = base64.b64decode(_bytes(cred.strip()), validate=True).decode(
                "utf-8").partition(":")
        except (binascii.Error, ValueError):  # not base64, not UTF-8
            return False
        want = settings.users.get(user)
        if want is not None and hmac.compare_digest(_bytes(password), want.encode()):
            return True
    return False


class Gate:
    """One listener's connections: how many are open (its cap), the refusals, and the
    ``Conn`` of each open one's transport (for the middleware)."""

    def __init__(self, server: Server, where: str) -> None:
        self.server = server
        self.open = 0
        self.lingering = 0  # refused ones whose 503 is being read
        self.refusals = Refusals(f"{server.what} {where}", log)
        # connections closed for what only a hostile or broken client does (an idle one
        # closed is no news): one line a minute
        self.expired = Refusals(f"{server.what} {where}", log, verb="closed")

    def __call__(self) -> Conn:
        return Conn(self)


class Conn(asyncio.Protocol):
    """A connection: refused (503, closed) when its listener has ``max_connections`` open,
    else aiohttp's handler inside, under two deadlines: ``header_timeout`` from the
    first byte of a request until its headers are in (the middleware ``begin``s it), and
    ``idle_timeout`` while no request is under way (from the start and from each
    request's ``end``), and ``idle_timeout`` too while what it was sent waits for it to
    read (its transport paused our writing). A connection past its deadline is closed."""

    __slots__ = ("busy", "gate", "got", "inner", "phase", "stall", "timer", "transport")

    def __init__(self, gate: Gate) -> None:
        self.gate = gate
        self.inner: asyncio.Protocol | None = None
        self.transport: asyncio.Transport | None = None
        self.timer: asyncio.TimerHandle | None = None
        self.busy = False
        self.phase = ""  # "idle_timeout", "header_timeout" or "" (a request is handled)
        self.stall: asyncio.TimerHandle | None = None  # while its writes wait for it
        self.got = 0  # bytes received since the last request's headers were in

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        gate, server = self.gate, self.gate.server
        runner = server.runner
        if gate.open >= server.settings.max_connections or runner is None or \
                runner.server is None:
            # a 503, the end of the stream, and what the client sends read until it
            # closes (closed with unread bytes, the socket would reset: the client might
            # never read the 503), at most LINGER seconds, at most ``max_connections`` so
            gate.refusals.refused("cap")
            transport.write(REFUSED)
            if gate.lingering >= server.settings.max_connections:
                transport.abort()
                return
            gate.lingering += 1
            self.phase = "refused"
            transport.write_eof()
            self.timer = asyncio.get_running_loop().call_later(LINGER, transport.abort)
            return
        gate.open += 1
        server.conns[transport] = self
        self.inner = runner.server()
        self.inner.connection_made(transport)
        self._wait("idle_timeout")

    def data_received(self, data: bytes) -> None:
        if self.inner is None or self.transport is None:
            return
        self.got += len(data)
        if self.got > MAX_HEAD:  # headers of 1 MB (aiohttp's own bound) on every
            # connection would hold 256 MB: a request is a few kB, nothing comes after
            # an event stream's request
            self.gate.expired.refused(f"with more than {MAX_HEAD >> 10} kB of headers")
            if self.busy:
                reset(self.transport)
            else:
                self.transport.write(TOO_LARGE)
                self.transport.close()
            return
        if not self.busy and self.phase != "header_timeout":
            self._wait("header_timeout")
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.inner is not None else None

    def pause_writing(self) -> None:
        """Its buffer is full: a client that reads nothing of it for ``idle_timeout``
        (an event stream or an answer it never reads) is closed, its buffer freed."""
        if self.inner is not None:
            self.inner.pause_writing()
            if self.stall is None:
                self.stall = asyncio.get_running_loop().call_later(
                    self.gate.server.settings.idle_timeout, self._stalled)

    def resume_writing(self) -> None:
        if self.stall is not None:
            self.stall.cancel()
            self.stall = None
        if self.inner is not None:
            self.inner.resume_writing()

    def _stalled(self) -> None:
        self.stall = None
        if self.transport is not None and self.inner is not None and \
                not self.transport.is_closing():
            self.gate.expired.refused(f"not reading what they were sent for "
                                      f"{self.gate.server.settings.idle_timeout:g} s")
            reset(self.transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel()
        if self.stall is not None:
            self.stall.cancel()
            self.stall = None
        if self.phase == "refused":
            self.gate.lingering -= 1
            self.phase = ""
        if self.inner is None:
            return
        self.gate.open -= 1
        if self.transport is not None:
            self.gate.server.conns.pop(self.transport, None)
        inner, self.inner = self.inner, None
        inner.connection_lost(exc)

    def begin(self) -> None:
        """A request's headers are in: no deadline while it is handled."""
        self.busy = True
        self.got = 0
        self._cancel()
        self.phase = ""

    def end(self) -> None:
        """The request was answered: idle until the next one's first byte."""
        self.busy = False
        if self.inner is not None:
            self._wait("idle_timeout")

    def _wait(self, phase: str) -> None:
        self._cancel()
        self.phase = phase
        self.timer = asyncio.get_running_loop().call_later(
            getattr(self.gate.server.settings, phase), self._expire)

    def _cancel(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None

    def _expire(self) -> None:
        self.timer = None
        t = self.transport
        if t is None or self.inner is None or t.is_closing():
            return
        settings = self.gate.server.settings
        if t.get_write_buffer_size():  # it does not read what it was sent
            self.gate.expired.refused(f"not reading what they were sent for "
                                      f"{settings.idle_timeout:g} s")
            reset(t)
            return
        if self.phase == "header_timeout":
            self.gate.expired.refused(f"with their headers not all in after "
                                      f"{settings.header_timeout:g} s")
        t.close()


class RequestLog:
    """aiohttp's logger for the listener's connections (``logger=``): a request it could
    not parse (no Host, a NUL in the path, huge headers, a bad chunk, HTTP/2's preface
    ...) is a count in ``refusals``' one line a minute, never a traceback; an error in a
    handler (a 500) too, its traceback only at debug level."""

    def __init__(self, refusals: Refusals) -> None:
        self.refusals = refusals

    def _count(self, args: tuple[Any, ...], kw: dict[str, Any]) -> None:
        exc = kw.get("exc_info")
        if not isinstance(exc, BaseException):
            exc = sys.exc_info()[1]
        if exc is None:
            return
        from aiohttp.http_exceptions import HttpProcessingError

        status = exc.code if isinstance(exc, HttpProcessingError) else 500
        self.refusals.refused(f"{type(exc).__name__} (HTTP {status})")
        if status == 500:
            log.debug("%s", args[0] if args else "error", exc_info=exc)

    def debug(self, *args: Any, **kw: Any) -> None:
        from aiohttp.http_exceptions import HttpProcessingError

        if isinstance(kw.get("exc_info"), HttpProcessingError):  # the first, not HTTP
            self._count(args, kw)

    def exception(self, *args: Any, **kw: Any) -> None:
        self._count(args, kw)

    error = warning = exception

    def info(self, *args: Any, **kw: Any) -> None:
        pass


class Server:
    """The listener: ``start`` binds (one-line ``UsageError`` when it cannot), ``stop``
    ends the event streams and closes it."""

    def __init__(self, settings: HttpSettings, source: Source, *, what: str = "--http") -> None:
        self.settings, self.source, self.what = settings, source, what
        self.assets = load_assets()
        self._runner: web.AppRunner | None = None
        self._listener: Listener | None = None
        self.conns: dict[asyncio.BaseTransport, Conn] = {}  # the open ones, every listener
        self.bad = Refusals(what, log, noun="request")
        self._pinger: asyncio.Task[None] | None = None
        self.address = ""  # http://HOST:PORT/ once listening

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._deadline, self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/events", self._events)
        app.router.add_get("/api/trend", self._trend)
        app.router.add_get("/metrics", self._metrics)
        return app

    async def start(self) -> None:
        self._runner = web.AppRunner(self.app(), access_log=None, handle_signals=False,
                                     shutdown_timeout=1.0, logger=RequestLog(self.bad))
        await self._runner.setup()
        try:
            await self.serve(self.settings, await self.bind(self.settings))
        except UsageError:
            await self._runner.cleanup()
            self._runner = None
            raise
        self._pinger = asyncio.create_task(self._ping())

    @property
    def runner(self) -> web.AppRunner | None:
        return self._runner

    async def bind(self, settings: HttpSettings) -> Listener:
        """A listener on ``settings``' address for these pages (``UsageError`` when it
        cannot be bound); ``serve`` makes it the one."""
        assert self._runner is not None
        listener = Listener(self._runner, settings.host, settings.port, self)
        try:
            await listener.start()
        except OSError as exc:
            await listener.stop()
            why = os.strerror(exc.errno) if exc.errno else str(exc)
            raise UsageError(f"{self.what}: cannot listen on {settings.host}:"
                             f"{settings.port}: {why}") from None
        return listener

    @property
    def listener(self) -> Listener | None:
        return self._listener

    async def serve(self, settings: HttpSettings, listener: Listener | None) -> None:
        """From now on: ``settings``' authentication, on ``listener`` (from ``bind``; None:
        none). The listener before closes; connections it took, event streams among
        them, stay open, unless the authentication changed: then they are closed (a page
        asks again, with the new credentials)."""
        was, old, self._listener, self.settings = self.settings, self._listener, listener, \
            settings
        if old is not None and old is not listener:
            await old.stop()
        if (was.token, dict(was.users)) != (settings.token, dict(settings.users)) and \
                self._runner is not None and self._runner.server is not None:
            await self._runner.server.shutdown(CLOSE_WAIT)
        self.address = ""
        if listener is not None and self._runner is not None and self._runner.addresses:
            host, port = self._runner.addresses[0][:2]
            host = f"[{host}]" if ":" in host else host
            self.address = f"http://{host}:{port}/"
            self.bad.what = f"{self.what} {host}:{port}"

    async def stop(self) -> None:
        self.source.hub.close()
        self.bad.flush()
        if self._pinger is not None:
            self._pinger.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pinger
        if self._runner is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._runner.cleanup(), 3.0)
            self._runner = None
        self._listener = None

    async def _ping(self) -> None:
        """Something on every event stream now and then: proxies keep idle ones open."""
        while True:
            await asyncio.sleep(PING)
            self.source.hub.publish("ping", "ping", "{}")

    # -- handlers -------------------------------------------------------------

    @web.middleware
    async def _deadline(self, request: web.Request, handler: Callable[[web.Request],
                        Awaitable[web.StreamResponse]]) -> web.StreamResponse:
        """A request's headers are in: its connection's header deadline is over, and its
        idle one starts again when it is answered."""
        conn = self.conns.get(request.transport) if request.transport is not None else None
        if conn is not None:
            conn.begin()
        try:
            return await handler(request)
        finally:
            if conn is not None:
                conn.end()

    def _misdirected(self, request: web.Request) -> web.StreamResponse | None:
        """On a loopback bind: 421 for a request to another host name (a page whose name
        was rebound to 127.0.0.1), 403 for one from another origin; None: it is ours."""
        s = self.settings
        if not s.loopback:
            return None
        host = request.headers.get("Host")
        if host is not None and not s.allows_host(_hostname("//" + host)):
            return web.Response(status=421, text="rtupoll: not this dashboard's host name "
                                "(--http-host, docs/web.md)\n", headers=SECURITY_HEADERS)
        origin = request.headers.get("Origin")
        if origin is not None and not s.allows_host(_hostname(origin)):
            return web.Response(status=403, text="rtupoll: a page of another origin "
                                "(docs/web.md)\n", headers=SECURITY_HEADERS)
        return None

    @web.middleware
    async def _guard(self, request: web.Request, handler: Callable[[web.Request], Awaitable[
            web.StreamResponse]]) -> web.StreamResponse:
        if request.method not in ("GET", "HEAD"):
            raise web.HTTPMethodNotAllowed(request.method, ["GET", "HEAD"],
                                           text="read-only: GET only\n")
        if (refused := self._misdirected(request)) is not None:
            return refused
        s = self.settings
        try:
            ok = authorised(s, request.headers, request.cookies, request.query)
        except (ValueError, UnicodeError, KeyError):  # a header that is not one
            raise web.HTTPBadRequest(text="rtupoll: a malformed header\n") from None
        if not ok:
            challenge = ", ".join((['Bearer realm="rtupoll"'] if s.token else []) +
                                  (['Basic realm="rtupoll"'] if s.users else []))
            return web.Response(status=401, text="rtupoll: authentication required "
                                "(docs/web.md)\n", headers={"WWW-Authenticate": challenge,
                                                            **SECURITY_HEADERS})
        if s.token and "token" in request.query and request.path == "/":
            # the link with the token, once: a cookie from now on, and the token out of
            # the address bar (and of the history)
            resp: web.StreamResponse = web.HTTPSeeOther("/")
            resp.set_cookie(COOKIE, cookie_value(s.token), httponly=True, samesite="Strict",
                            path="/")
            return resp
        resp = await handler(request)
        resp.headers.update(SECURITY_HEADERS)
        return resp

    async def _index(self, request: web.Request) -> web.StreamResponse:
        body, ctype = self.assets["index.html"]
        return web.Response(body=body, headers={"Content-Type": ctype,
                                                     "Cache-Control": "no-cache"})

    async def _static(self, request: web.Request) -> web.StreamResponse:
        got = self.assets.get(request.match_info["name"])
        if got is None:
            raise web.HTTPNotFound(text="not found\n")
        return web.Response(body=got[0], headers={"Content-Type": got[1],
                                                       "Cache-Control": "no-cache"})

    async def _state(self, request: web.Request) -> web.StreamResponse:
        return self._json(self.source.snapshot())

    async def _trend(self, request: web.Request) -> web.StreamResponse:
        key, field = request.query.get("device", ""), request.query.get("field", "")
        if not key or not field:
            raise web.HTTPBadRequest(text="give device=KEY&field=NAME\n")
        return self._json(self.source.trend(key, field))

    async def _metrics(self, request: web.Request) -> web.StreamResponse:
        got = self.source.metrics(request.headers.get("Accept", ""))
        if got is None:
            raise web.HTTPNotFound(text="no metrics here\n")
        body, ctype = got
        resp = web.Response(body=body)
        resp.headers["Content-Type"] = ctype
        return resp

    def _json(self, obj: Any) -> web.StreamResponse:
        return web.Response(text=to_json(obj), content_type="application/json",
                                 headers={"Cache-Control": "no-store"})

    def _snapshot(self) -> bytes:
        return encode("state", to_json(self.source.snapshot()))

    async def _events(self, request: web.Request) -> web.StreamResponse:
        hub = self.source.hub
        resp = web.StreamResponse(headers={
            "Content-Type": "text/event-stream", "Cache-Control": "no-store",
            "X-Accel-Buffering": "no", **SECURITY_HEADERS})
        await resp.prepare(request)
        box = hub.join()  # and its snapshot at once, in the same step
        try:
            await resp.write(b"retry: 2000\n" + self._snapshot())
            while not hub.closed:
                await box.wake.wait()
                if hub.closed:
                    break
                if box.behind:  # it stopped reading for a while: a snapshot, no backlog
                    hub.rejoin(box)
                    await resp.write(self._snapshot())
                else:
                    await resp.write(box.take())
        except (ConnectionError, RuntimeError):  # the browser went away
            pass
        finally:
            hub.clients.discard(box)
        return resp


def _hostname(url: str) -> str:
    """The host name of an Origin or ``//`` + Host (lower-case, no port; "" if none)."""
    try:
        return urlsplit(url).hostname or ""
    except ValueError:
        return ""


class Listener(web.BaseSite):
    """A TCP listener whose connections each go through a ``Conn`` of its ``Gate``;
    asyncio's accept errors (out of descriptors) counted there, never a traceback."""

    def __init__(self, runner: web.AppRunner, host: str, port: int, server: Server) -> None:
        super().__init__(runner)
        self.host, self.wanted = host, port
        self.gate = Gate(server, f"{host}:{port}")
        self._unwatch: Callable[[], None] | None = None

    @property
    def name(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.wanted}"

    async def start(self) -> None:
        await super().start()
        self._server = server = await asyncio.get_running_loop().create_server(
            self.gate, self.host, self.wanted, backlog=self._backlog, reuse_address=True)
        sockets = server.sockets
        if sockets:
            port = sockets[0].getsockname()[1]
            host = f"[{self.host}]" if ":" in self.host else self.host
            self.gate.refusals.what = self.gate.expired.what = \
                f"{self.gate.server.what} {host}:{port}"
        self._unwatch = watch(sockets, self.gate.refusals)

    async def stop(self) -> None:
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        self.gate.refusals.flush()
        self.gate.expired.flush()
        await super().stop()
