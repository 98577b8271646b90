"""``first_of``: the first of several waits ends the others, none outlives the call, the
first's error is itself (no ExceptionGroup). Events and a zero timeout: no wall clock."""

from __future__ import annotations

import asyncio

import pytest

from rtupoll.jobs.race import first_of


class Waiter:
    """A wait that says how it ended."""

    def __init__(self) -> None:
        self.event = asyncio.Event()
        self.ended = ""

    async def wait(self, fail: Exception | None = None) -> str:
        try:
            await self.event.wait()
        except asyncio.CancelledError:
            self.ended = "cancelled"
            raise
        if fail is not None:
            self.ended = "failed"
            raise fail
        self.ended = "done"
        return "done"


def test_the_first_to_end_wins_and_the_others_are_cancelled() -> None:
    async def go() -> tuple[int | None, list[str], int]:
        a, b, c = Waiter(), Waiter(), Waiter()
        loop = asyncio.get_running_loop()
        loop.call_soon(b.event.set)
        won = await first_of(a.wait(), b.wait(), c.wait())
        others = len([t for t in asyncio.all_tasks() if t is not asyncio.current_task()])
        return won, [a.ended, b.ended, c.ended], others

    won, ended, others = asyncio.run(go())
    assert won == 1
    assert ended == ["cancelled", "done", "cancelled"]
    assert others == 0  # nothing outlives the call


def test_the_timeout_cancels_them_all() -> None:
    async def go() -> tuple[int | None, list[str]]:
        a, b = Waiter(), Waiter()
        won = await first_of(a.wait(), b.wait(), timeout=0)
        return won, [a.ended, b.ended]

    assert asyncio.run(go()) == (None, ["cancelled", "cancelled"])


def test_the_firsts_error_is_raised_as_itself() -> None:
    async def go() -> list[str]:
        a, b = Waiter(), Waiter()
        asyncio.get_running_loop().call_soon(a.event.set)
        with pytest.raises(ValueError, match="the port went away"):
            await first_of(a.wait(ValueError("the port went away")), b.wait())
        return [a.ended, b.ended]

    assert asyncio.run(go()) == ["failed", "cancelled"]


def test_cancelling_the_caller_cancels_every_wait() -> None:
    async def go() -> list[str]:
        a, b = Waiter(), Waiter()
        racing = asyncio.create_task(first_of(a.wait(), b.wait()))
        await asyncio.sleep(0)
        racing.cancel()
        with pytest.raises(asyncio.CancelledError):
            await racing
        return [a.ended, b.ended]

    assert asyncio.run(go()) == ["cancelled", "cancelled"]
