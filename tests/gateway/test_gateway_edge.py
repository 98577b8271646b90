"""The gateway at the edge, in-process on real loopback sockets: a client that has gone
before its turn has its requests dropped unsent (writes included), and connections
over a cap are closed as they come. The line is one the test holds: a transaction
ends when the test says, so which request waits behind which is decided, not timed.
(End to end with the real CLI and the simulator: test_gateway_hostile.py.)"""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.gateway.server import Gateway
from rtupoll.gateway.turns import Turns
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.rtu import Framing
from tests.gateway.test_gateway_guard import site

HANG = 30  # a hang guard: what is awaited comes, or the test is broken


class HeldLine:
    """A line whose transactions end when ``release`` is set; it records what reached it."""

    framing = Framing(9600)

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []
        self.started = asyncio.Event()
        self.release = asyncio.Event()

    async def open(self) -> None: ...
    async def close(self) -> None: ...

    def late(self, unit: int) -> int:
        return 0

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0, idle_gap: float | None = None) -> bytes:
        self.sent.append((unit, pdu))
        self.started.set()
        await self.release.wait()
        return bytes((pdu[0], 2, 0, 7)) if pdu[0] in (3, 4) else pdu


@asynccontextmanager
async def gateway(**serve: Any) -> AsyncIterator[tuple[Gateway, HeldLine, list[str]]]:
    line, logs = HeldLine(), []  # type: ignore[var-annotated]
    bp = Scheduler(site(), open_bus=lambda _c: line).buses[0]  # type: ignore[arg-type,return-value]
    gw = Gateway(ServeConfig("127.0.0.1", 0, **serve), bp, Turns(), log=logs.append)
    await gw.start()
    try:
        yield gw, line, logs
    finally:
        line.release.set()
        await gw.stop()


def mbap(tid: int, unit: int, pdu: str) -> bytes:
    body = bytes.fromhex(pdu)
    return struct.pack(">HHHB", tid, 0, len(body) + 1, unit) + body


READ = "03 00 00 00 01"  # FC 3, one register
WRITE = "06 00 10 12 34"  # FC 6: holding 0x0010 := 0x1234


async def until(condition: Any) -> None:
    async with asyncio.timeout(HANG):
        while not condition():
            await asyncio.sleep(0.005)


async def reply_to(r: asyncio.StreamReader) -> bytes:
    head = await asyncio.wait_for(r.readexactly(7), HANG)
    return await r.readexactly(struct.unpack(">H", head[4:6])[0] - 1)


def test_a_write_whose_client_left_before_its_turn_never_reaches_the_line() -> None:
    async def main() -> tuple[list[tuple[int, bytes]], list[str], bytes]:
        async with gateway() as (gw, line, logs):
            port = gw.address[1]
            r1, w1 = await asyncio.open_connection("127.0.0.1", port)
            w1.write(mbap(1, 3, READ))  # on the line, held there
            await asyncio.wait_for(line.started.wait(), HANG)
            _, w2 = await asyncio.open_connection("127.0.0.1", port)
            w2.write(mbap(1, 3, WRITE))  # waits for its turn ...
            await w2.drain()
            w2.close()  # ... and its client leaves
            await until(lambda: any("gone before its turn" in x for x in logs))
            line.release.set()
            first = await reply_to(r1)  # the one on the line completes, answered
            w1.close()
            await until(lambda: not gw.clients[1].connected)
            assert gw.clients[1].record()["dropped"] == 1  # counted for the client too
            assert "1 dropped unsent" in gw.clients[1].summary()
            return list(line.sent), list(logs), first

    sent, logs, first = asyncio.run(main())
    assert sent == [(3, bytes.fromhex(READ))]  # the write never went out
    assert first == bytes.fromhex("03 02 00 07")
    gone = [x for x in logs if "gone before its turn" in x]
    assert len(gone) == 1 and gone[0].endswith("1 request dropped unsent (1 write)"), logs


def test_requests_not_read_yet_behind_a_hang_up_are_dropped_when_their_turn_comes() -> None:
    """``client_queue`` 1: while its first request is on the line, rtupoll reads no more
    of this client, so its hang-up is behind requests not read yet; as the next one
    gets its turn the socket shows the client gone, and both writes stay off the line."""

    async def main() -> tuple[list[tuple[int, bytes]], list[str]]:
        async with gateway(client_queue=1) as (gw, line, logs):
            s = socket.create_connection(gw.address)
            s.sendall(mbap(1, 3, READ))
            await asyncio.wait_for(line.started.wait(), HANG)
            s.sendall(mbap(2, 3, WRITE) + mbap(3, 3, WRITE))
            await asyncio.sleep(0.05)  # (read or not by then: either way held)
            s.close()
            line.release.set()
            await until(lambda: any("gone before its turn" in x for x in logs))
            await until(lambda: not gw.clients[0].connected)
            return list(line.sent), list(logs)

    sent, logs = asyncio.run(main())
    assert sent == [(3, bytes.fromhex(READ))]
    gone = [x for x in logs if "gone before its turn" in x]
    assert len(gone) == 1 and gone[0].endswith("2 requests dropped unsent (2 writes)"), logs


def test_connections_over_the_caps_are_closed_as_they_come_and_logged_once() -> None:
    async def main() -> tuple[list[bytes], list[bytes], list[str], int, bytes, int]:
        async with gateway(max_clients=3, max_per_address=2) as (gw, line, logs):
            line.release.set()  # the line answers at once here
            port = gw.address[1]
            kept = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
            over = [await asyncio.open_connection("127.0.0.1", port) for _ in range(3)]
            ends = [await asyncio.wait_for(r.read(100), HANG) for r, _ in over]  # closed
            # another address on the loopback: the listener has room for one more
            other = [await asyncio.open_connection("127.0.0.1", port,
                                                   local_addr=("127.0.0.2", 0))
                     for _ in range(2)]
            full = await asyncio.wait_for(other[1][0].read(100), HANG)  # the 4th: over 3
            replies = []
            for r, w in [*kept, other[0]]:  # the connections kept are served
                w.write(mbap(9, 3, READ))
                replies.append(await reply_to(r))
            for _, w in [*kept, *over, *other]:
                w.close()
            return [*ends, full], replies, list(logs), gw.refused_connections, \
                bytes.fromhex("03 02 00 07"), port

    ends, replies, logs, refused, want, port = asyncio.run(main())
    assert ends == [b""] * 4 and replies == [want] * 3 and refused == 4
    lines = [x for x in logs if "refused" in x]
    assert len(lines) == 1, logs  # once per interval, whatever the count
    assert lines[0].startswith(f"gateway tcp://127.0.0.1:{port}: refused 1 connection: 1 from "
                               "127.0.0.1 over max_per_address 2 (counted from now on"), lines
