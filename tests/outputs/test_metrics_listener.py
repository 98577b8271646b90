"""The ``--metrics`` listener (``rtupoll.outputs.metrics_listener``) against real sockets:
what it answers, and the dashboard's limits holding for it (connections capped with a
503, idle and slow-header connections closed, huge headers 431, a client that does not
read reset), each refusal counted, never a traceback."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

import pytest

from rtupoll.outputs.metrics_listener import MAX_HEAD, MetricsListener

BODY = b"# a metrics page\nrtupoll_device_up 1\n"


def render(accept: str) -> tuple[bytes, str]:
    return BODY + accept.encode(), "text/plain; version=0.0.4"


@contextlib.asynccontextmanager
async def listening(**limits: Any) -> AsyncIterator[MetricsListener]:
    listener = MetricsListener("127.0.0.1", 0, render, **limits)
    await listener.start()
    try:
        yield listener
    finally:
        await listener.stop()


async def connect(listener: MetricsListener) -> tuple[asyncio.StreamReader,
                                                      asyncio.StreamWriter]:
    port = int(listener.address.rsplit(":", 1)[1].split("/")[0])
    return await asyncio.open_connection("127.0.0.1", port)


async def exchange(listener: MetricsListener, request: bytes) -> bytes:
    reader, writer = await connect(listener)
    writer.write(request)
    try:
        return await asyncio.wait_for(reader.read(), 30)  # a hang guard, not a timing claim
    finally:
        writer.close()


def test_what_it_answers() -> None:
    async def main() -> None:
        async with listening() as listener:
            assert listener.address.startswith("http://127.0.0.1:")
            got = await exchange(listener, b"GET /metrics?x=1 HTTP/1.1\r\nHost: a\r\n"
                                 b"Accept: text/plain\r\n\r\n")
            head, _, body = got.partition(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 200 OK\r\n")
            assert b"Content-Type: text/plain; version=0.0.4" in head
            assert body == BODY + b"text/plain"  # the Accept header reaches the renderer
            assert f"Content-Length: {len(body)}".encode() in head
            got = await exchange(listener, b"HEAD /metrics HTTP/1.1\r\n\r\n")
            assert got.startswith(b"HTTP/1.1 200") and got.endswith(b"\r\n\r\n")
            assert (await exchange(listener, b"GET / HTTP/1.1\r\n\r\n")).endswith(
                b"metrics at /metrics\n")
            assert (await exchange(listener, b"GET /x HTTP/1.1\r\n\r\n")).startswith(
                b"HTTP/1.1 404")
            assert (await exchange(listener, b"POST /metrics HTTP/1.1\r\n\r\n")).startswith(
                b"HTTP/1.1 405")

    asyncio.run(main())


def test_more_than_max_connections_get_a_503_and_are_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> None:
        async with listening(max_connections=2) as listener:
            held = [await connect(listener) for _ in range(2)]
            while listener.open < 2:  # both accepted
                await asyncio.sleep(0.01)
            got = await exchange(listener, b"GET /metrics HTTP/1.1\r\n\r\n")
            assert got.startswith(b"HTTP/1.1 503 Service Unavailable\r\n")
            assert listener.refusals.counts["cap"] == 1
            for _, w in held:
                w.close()
            while listener.open:
                await asyncio.sleep(0.01)
            ok = await exchange(listener, b"GET /metrics HTTP/1.1\r\n\r\n")
            assert ok.startswith(b"HTTP/1.1 200")  # room again

    with caplog.at_level(logging.WARNING, logger="rtupoll"):
        asyncio.run(main())
    assert any("refused 1 connection" in r.getMessage() for r in caplog.records), \
        [r.getMessage() for r in caplog.records]


def test_an_idle_connection_is_closed_quietly_and_slow_headers_counted() -> None:
    async def main() -> None:
        async with listening(idle_timeout=0.2, header_timeout=0.2) as listener:
            reader, writer = await connect(listener)
            assert await asyncio.wait_for(reader.read(), 30) == b""  # closed, nothing said
            writer.close()
            assert listener.expired.total == 0  # an idle connection is no news
            reader, writer = await connect(listener)
            writer.write(b"GET /metrics HTTP/1.1\r\nHost: a\r\n")  # and never the end
            assert await asyncio.wait_for(reader.read(), 30) == b""
            writer.close()
            assert list(listener.expired.counts) == [
                "with their headers not all in after 0.2 s"]

    asyncio.run(main())


def test_headers_beyond_the_bound_get_431() -> None:
    async def main() -> None:
        async with listening() as listener:
            reader, writer = await connect(listener)
            writer.write(b"GET /metrics HTTP/1.1\r\n")
            filler = b"X-A: " + b"a" * 1000 + b"\r\n"
            with contextlib.suppress(ConnectionError):
                for _ in range(MAX_HEAD // len(filler) + 2):
                    writer.write(filler)
                await writer.drain()
            got = await asyncio.wait_for(reader.read(), 30)
            writer.close()
            assert got.startswith(b"HTTP/1.1 431")
            assert listener.expired.total == 1

    asyncio.run(main())


def test_a_client_that_reads_nothing_of_a_large_answer_is_reset() -> None:
    big = b"x" * (64 << 20)  # more than the socket buffers hold

    async def main() -> None:
        listener = MetricsListener("127.0.0.1", 0, lambda accept: (big, "text/plain"),
                                   idle_timeout=0.3)
        await listener.start()
        try:
            _, writer = await connect(listener)
            writer.write(b"GET /metrics HTTP/1.1\r\n\r\n")
            deadline = asyncio.get_running_loop().time() + 30  # a hang guard
            while not listener.expired.total:  # it never reads: reset after idle_timeout
                assert asyncio.get_running_loop().time() < deadline
                await asyncio.sleep(0.05)
            assert list(listener.expired.counts) == [
                "not reading what they were sent for 0.3 s"]
            writer.close()
        finally:
            await listener.stop()

    asyncio.run(main())
