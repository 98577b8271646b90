"""The first of several waits, in structured concurrency: ``first_of`` runs coroutines
as the tasks of one ``asyncio.TaskGroup``; when one ends, the others are cancelled, and
none outlives the call (a bus idling until it is due, woken or stopped; ``poll --once``
until its scan ends or a signal stops it)."""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any


async def first_of(*waits: Coroutine[Any, Any, Any], timeout: float | None = None
                   ) -> int | None:
    """Run ``waits`` together until the first ends; the others are cancelled. Its index,
    or None when ``timeout`` seconds passed first (all cancelled). An error the first
    raises is raised here as itself, not in an ``ExceptionGroup``."""
    tasks: list[asyncio.Task[Any]] = []
    ended: list[int] = []

    def done(task: asyncio.Task[Any]) -> None:
        if not ended and not task.cancelled():
            ended.append(tasks.index(task))
        for other in tasks:
            if other is not task:
                other.cancel()

    try:
        async with asyncio.timeout(timeout), asyncio.TaskGroup() as group:
            for wait in waits:  # all made before any runs: each callback sees them all
                task = group.create_task(wait)
                task.add_done_callback(done)
                tasks.append(task)
    except TimeoutError:
        return None
    except BaseExceptionGroup as errors:
        raise _first(errors) from None
    return ended[0] if ended else None


def _first(errors: BaseExceptionGroup[BaseException]) -> BaseException:
    first = errors.exceptions[0]
    return _first(first) if isinstance(first, BaseExceptionGroup) else first
