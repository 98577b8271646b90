"""Fair turns on the line (rtupoll.gateway.turns): nothing here reads a clock, so the
rules are checked by counting who got each turn."""

from __future__ import annotations

import asyncio
import itertools

from rtupoll.gateway.turns import POLLER, Turns


async def _hammer(turns: Turns, who: object, log: list[object], n: int) -> None:
    for _ in range(n):
        async with turns.turn(who):
            log.append(who)
            await asyncio.sleep(0)  # a transaction: others queue up meanwhile


def test_poller_and_a_hammering_client_alternate() -> None:
    async def main() -> list[object]:
        turns, log = Turns(), []  # type: ignore[var-annotated]
        await asyncio.gather(_hammer(turns, POLLER, log, 50), _hammer(turns, "c1", log, 50))
        return log

    log = asyncio.run(main())
    assert len(log) == 100
    # once both wait, nobody gets two turns in a row
    assert all(a != b for a, b in itertools.pairwise(log[2:]))


def test_clients_share_their_half_round_robin() -> None:
    async def main() -> list[object]:
        turns, log = Turns(), []  # type: ignore[var-annotated]
        await asyncio.gather(_hammer(turns, POLLER, log, 40), _hammer(turns, "a", log, 40),
                             _hammer(turns, "b", log, 40))
        return log

    log = asyncio.run(main())
    first = log[:80]  # while all three keep asking
    assert first.count(POLLER) >= 38  # the poller keeps about half of the line
    clients = [w for w in first if w is not POLLER]
    assert abs(clients.count("a") - clients.count("b")) <= 2


def test_an_idle_poller_leaves_the_line_to_clients_and_cancel_is_clean() -> None:
    async def main() -> tuple[list[object], int]:
        turns, log = Turns(), []  # type: ignore[var-annotated]
        hold = asyncio.Event()

        async def holder() -> None:
            async with turns.turn("a"):
                await hold.wait()

        first = asyncio.create_task(holder())
        await asyncio.sleep(0)
        waiter = asyncio.create_task(_hammer(turns, POLLER, log, 1))
        await asyncio.sleep(0)
        waiter.cancel()  # gives up while queued: must not keep a place in the queue
        await asyncio.gather(waiter, return_exceptions=True)
        hold.set()
        await first
        await _hammer(turns, "b", log, 5)
        return log, turns.waiting

    log, waiting = asyncio.run(main())
    assert log == ["b"] * 5 and waiting == 0
