"""The ``--metrics`` listener: ``/metrics`` over HTTP/1.1 with no web framework.

``poll --metrics`` imports no aiohttp: measured with ``poll --simulate --metrics``,
aiohttp's import alone takes resident memory from 34 to 47 MB and the first scrape
from 0.48 to 0.85 s, where the whole of what Prometheus asks is one GET. The
dashboard (``poll --http``, aiohttp) serves the same exposition at its ``/metrics``
(``outputs.metrics.Exporter.render``: one handler's body for both listeners).

One request a connection (``Connection: close``): ``GET``/``HEAD /metrics``, ``/`` says
where they are, anything else 404, other methods 405. The limits are the dashboard's
(``config.http_settings``' defaults, and the bytes of its refusals, defined here for
both): at most ``max_connections`` open (more get a 503 and are closed), nothing sent
within ``idle_timeout`` of connecting or headers not all in within ``header_timeout`` of
their first byte: closed; headers beyond ``MAX_HEAD``: 431; an answer the client does
not read for ``idle_timeout``: reset. Refused and closed connections are counted and
logged once a minute (``rtupoll.refusals``), asyncio's accept errors too.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
from collections.abc import Callable

from rtupoll.config.http_settings import HEADER_TIMEOUT, IDLE_TIMEOUT, MAX_CONNECTIONS
from rtupoll.refusals import Refusals, watch

log = logging.getLogger("rtupoll.metrics")

LINGER = 1.0  # seconds a refused connection is given to read its 503
MAX_HEAD = 32 << 10  # bytes a connection may send from one request's headers to the next
_BIG = b"rtupoll: request headers too large\n"
TOO_LARGE = (b"HTTP/1.1 431 Request Header Fields Too Large\r\n"
             b"Content-Type: text/plain; charset=utf-8\r\nContent-Length: %d\r\n"
             b"Connection: close\r\n\r\n%s" % (len(_BIG), _BIG))
_BUSY = b"rtupoll: too many connections, retry later\n"
REFUSED = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain; charset=utf-8\r\n"
           b"Content-Length: %d\r\nConnection: close\r\nRetry-After: 10\r\n\r\n%s"
           % (len(_BUSY), _BUSY))

Render = Callable[[str], tuple[bytes, str]]  # the Accept header -> (body, content type)


def reset(transport: asyncio.WriteTransport) -> None:
    """Close a connection whose client does not read: a reset (SO_LINGER 0), so that
    neither the transport's buffer nor the kernel's queue of it outlives the close."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


def answer(method: str, path: str, accept: str, render: Render) -> tuple[str, str, bytes]:
    """``(status, content type, body)`` for a request of this listener."""
    if method not in ("GET", "HEAD"):
        return "405 Method Not Allowed", "text/plain", b"GET only\n"
    if path == "/metrics":
        body, ctype = render(accept)
        return "200 OK", ctype, body
    if path == "/":
        return "200 OK", "text/plain; charset=utf-8", b"rtupoll: metrics at /metrics\n"
    return "404 Not Found", "text/plain", b"not found: try /metrics\n"


class MetricsListener:
    """``/metrics`` on ``host:port`` from ``render``, under the limits above."""

    def __init__(self, host: str, port: int, render: Render, *, what: str = "--metrics",
                 header_timeout: float = HEADER_TIMEOUT, idle_timeout: float = IDLE_TIMEOUT,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        self.host, self.port, self.render = host, port, render
        self.header_timeout, self.idle_timeout = header_timeout, idle_timeout
        self.max_connections = max_connections
        where = f"{what} {host}:{port}"
        self.refusals = Refusals(where, log)
        self.expired = Refusals(where, log, verb="closed")  # what only a hostile client does
        self.open = 0  # connections being answered
        self.lingering = 0  # refused ones whose 503 is being read
        self.address = ""  # http://HOST:PORT/metrics once listening
        self._server: asyncio.Server | None = None
        self._unwatch: Callable[[], None] | None = None

    async def start(self) -> None:
        """Listen (``OSError`` when the address cannot be bound)."""
        # [::]: IPv6 and IPv4 (asyncio binds "::" IPv6-only)
        hosts = ["::", "0.0.0.0"] if self.host == "::" else self.host
        self._server = await asyncio.start_server(self._serve, hosts, self.port,
                                                  limit=MAX_HEAD)
        sock = self._server.sockets[0].getsockname()
        host = f"[{sock[0]}]" if ":" in sock[0] else sock[0]
        self.address = f"http://{host}:{sock[1]}/metrics"
        self.refusals.what = self.expired.what = self.refusals.what.rsplit(" ", 1)[0] + \
            f" {host}:{sock[1]}"
        self._unwatch = watch(self._server.sockets, self.refusals)

    async def stop(self) -> None:
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        self.refusals.flush()
        self.expired.flush()
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
            self._server = None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.open >= self.max_connections:
            await self._refuse(reader, writer)
            return
        self.open += 1
        try:
            await self._one(reader, writer)
        except (ConnectionError, UnicodeError):
            pass
        finally:
            self.open -= 1
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), LINGER)

    async def _refuse(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A 503, then the lingering close (``_linger``)."""
        self.refusals.refused("cap")
        writer.write(REFUSED)
        await self._linger(reader, writer)

    async def _linger(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """After an answer sent before the request was read whole (503, 431): the end of
        the stream, and what the client sends read until it closes (closed with unread
        bytes, the socket would reset: the client might never read the answer), at most
        ``LINGER`` seconds, at most ``max_connections`` connections so."""
        if self.lingering >= self.max_connections:
            reset(writer.transport)
            return
        self.lingering += 1
        try:
            with contextlib.suppress(Exception):
                writer.write_eof()
                async with asyncio.timeout(LINGER):
                    while await reader.read(MAX_HEAD):
                        pass
        finally:
            self.lingering -= 1
            writer.transport.abort()

    async def _one(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One request: its first byte within ``idle_timeout``, its headers within
        ``header_timeout`` of it; answered, and the answer read within ``idle_timeout``."""
        try:
            first = await asyncio.wait_for(reader.readexactly(1), self.idle_timeout)
        except (TimeoutError, asyncio.IncompleteReadError):
            return  # an idle connection closed: no news
        try:
            head = first + await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"),
                                                  self.header_timeout)
        except TimeoutError:
            self.expired.refused(f"with their headers not all in after "
                                 f"{self.header_timeout:g} s")
            return
        except asyncio.LimitOverrunError:
            self.expired.refused(f"with more than {MAX_HEAD >> 10} kB of headers")
            writer.write(TOO_LARGE)
            await self._linger(reader, writer)
            return
        except asyncio.IncompleteReadError:
            return
        request, *header_lines = head.decode("latin-1").split("\r\n")
        method, _, rest = request.partition(" ")
        path = rest.partition(" ")[0].partition("?")[0]
        accept = next((v.strip() for k, _, v in (h.partition(":") for h in header_lines)
                       if k.strip().lower() == "accept"), "")
        status, ctype, body = answer(method, path, accept, self.render)
        writer.write(f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\n"
                     f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
                     .encode("latin-1"))
        if method != "HEAD":
            writer.write(body)
        try:
            await asyncio.wait_for(writer.drain(), self.idle_timeout)
        except TimeoutError:
            self.expired.refused(f"not reading what they were sent for "
                                 f"{self.idle_timeout:g} s")
            reset(writer.transport)
