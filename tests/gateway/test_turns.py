"""Fair turns on the line (rtupoll.gateway.turns): nothing here reads a clock, so the
rules are checked by counting who got each turn."""

from __future__ import annotations

import asyncio
import itertools

from rtupoll.gateway.turns import POLLER, REMEMBERED, Places, Turns


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


def test_a_clients_first_place_is_its_own_and_the_rest_are_shared() -> None:
    places = Places(shared=2)
    assert [places.take("hog") for _ in range(4)] == [True, True, True, False]
    assert places.used == 2 and places.held("hog") == 3
    # the shared places are gone, yet a client with nothing waiting gets its own
    assert places.take("a") and places.take("b")
    assert not places.take("a")  # a second one would be shared: none left
    places.give_back("hog")  # one of the hog's answered: a shared place comes free
    assert places.used == 1 and places.take("a") and places.held("a") == 2
    for who, n in (("hog", 2), ("a", 2), ("b", 1)):
        for _ in range(n):
            places.give_back(who)
    assert places.used == 0 and places.total == 0
    places.give_back("nobody")  # (a client holding nothing gives back nothing)
    assert places.used == 0 and places.take("nobody")


def test_fewer_shared_places_after_a_reload_admit_nothing_shared_until_below() -> None:
    places = Places(shared=3)
    assert all(places.take("a") for _ in range(4))  # its own and three shared
    places.shared = 1  # a SIGHUP's smaller queue:
    assert not places.take("a") and places.take("b")  # b's own place is still there
    places.give_back("a")
    places.give_back("a")
    assert not places.take("a")  # one shared still held: the one allowed
    places.give_back("a")
    assert places.take("a")


def test_a_client_that_asks_now_and_then_goes_ahead_of_one_that_hammers() -> None:
    """The hammering client waits again the moment its turn ends, so it is always
    first in line; the client whose last turn is longest ago goes first all the same."""
    async def main() -> list[object]:
        turns, log = Turns(), []  # type: ignore[var-annotated]
        line = asyncio.Event()

        async def take(who: object, hold: asyncio.Event | None = None) -> None:
            async with turns.turn(who):
                log.append(who)
                if hold is not None:
                    await hold.wait()

        await take("h")  # the hammer has had a turn just now; "o" has not had one
        poller = asyncio.create_task(take(POLLER, line))  # the poller's cycle holds the line
        await asyncio.sleep(0)
        waiting = [asyncio.create_task(take("h")), asyncio.create_task(take("o"))]
        await asyncio.sleep(0)  # both wait, "h" first
        line.set()
        await asyncio.gather(poller, *waiting)
        return log

    assert asyncio.run(main()) == ["h", POLLER, "o", "h"]


def test_a_forgotten_client_counts_as_never_served() -> None:
    turns = Turns()

    async def main() -> None:
        for n in range(REMEMBERED + 10):
            async with turns.turn(n):
                pass

    asyncio.run(main())
    assert len(turns._last) == REMEMBERED  # bounded, however many clients came and went
