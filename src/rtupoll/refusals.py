"""Connections a listener refused: counted, and logged once per interval, never a traceback.

A listener (the dashboard's ``--http``, the gateway's ``--serve``) refuses a connection
when it is at its cap, or cannot take it at all: asyncio's accept loop, out of file
descriptors (``EMFILE``, ``ENFILE``) or memory (``ENOBUFS``, ``ENOMEM``), hands the
error to the event loop's exception handler, whose default logs a traceback for every
attempt (hundreds a second while the descriptors are gone). ``watch`` puts the public
way to handle that in place, ``loop.set_exception_handler``: the errors of a watched
listening socket go to its ``Refusals``; every other context goes on to the handler
that was there before (or the loop's default), unchanged.

``Refusals`` counts by reason and logs one line at the first refusal and then at most
one line per ``every`` seconds with what was refused since the line before, so stderr
grows by a line a minute whatever the load::

    refusals = Refusals("--http 127.0.0.1:8080", log)
    unwatch = watch(server.sockets, refusals)   # on the running loop, once listening
    refusals.refused("cap")                     # the listener's own refusals, too
    ...
    unwatch()                                   # before the listener closes
    refusals.flush()                            # what is counted and not yet logged
"""

from __future__ import annotations

import asyncio
import errno
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any, Protocol

EVERY = 60.0  # seconds between two lines about one listener's refusals
# what a reason is called in the log line
REASONS = {"cap": "at the connection cap", "EMFILE": "out of file descriptors (EMFILE)",
           "ENFILE": "out of file descriptors system-wide (ENFILE)",
           "ENOBUFS": "out of buffer space (ENOBUFS)", "ENOMEM": "out of memory (ENOMEM)"}


def reason(exc: OSError) -> str:
    """An accept's error as a reason: its errno's name (``EMFILE``), else ``OSError``."""
    return errno.errorcode.get(exc.errno or 0, "OSError")


class Refusals:
    """One listener's refused connections: ``total``, ``counts`` by reason, and a log line
    at the first and then at most one per ``every`` seconds (the counts since the last
    line; what is left when refusals stop is logged ``every`` seconds after the last line,
    when an event loop runs, else by ``flush``)."""

    def __init__(self, what: str, log: logging.Logger, *, every: float = EVERY,
                 clock: Callable[[], float] = time.monotonic,
                 extra: dict[str, Any] | None = None, noun: str = "connection",
                 verb: str = "refused") -> None:
        """``what`` names the listener in the line (``--http 127.0.0.1:8080``); ``noun``
        and ``verb`` what happened (``request``: "refused 3 requests"; ``message`` and
        ``dropped``: "dropped 1 message")."""
        self.what, self.log, self.every, self.clock = what, log, every, clock
        self.noun, self.verb = noun, verb
        self.extra = extra if extra is not None else {"event": "refused"}
        self.total = 0
        self.counts: Counter[str] = Counter()  # since the start
        self._unlogged: Counter[str] = Counter()
        self._last: float | None = None  # when the last line was logged
        self._timer: asyncio.TimerHandle | None = None

    def refused(self, why: str) -> None:
        """One connection refused for ``why`` (``cap``, ``EMFILE``, ...)."""
        self.total += 1
        self.counts[why] += 1
        self._unlogged[why] += 1
        now = self.clock()
        if self._last is None or now - self._last >= self.every:
            self.flush()
        elif self._timer is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:
                return
            self._timer = loop.call_later(self._last + self.every - now, self._due)

    def _due(self) -> None:
        self._timer = None
        self.flush()

    def flush(self) -> None:
        """Log what was refused and not logged yet (nothing: no line)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if not self._unlogged:
            return
        n = sum(self._unlogged.values())
        parts = ", ".join(f"{c} {REASONS.get(k, k)}" for k, c in self._unlogged.most_common())
        since = "" if self._last is None else f" in the last {self.clock() - self._last:.3g} s"
        first = " (counted from now on, one line per " \
            f"{self.every:g} s)" if self._last is None else ""
        self.log.warning("%s: %s %d %s%s%s: %s%s", self.what, self.verb, n, self.noun,
                         "" if n == 1 else "s", since, parts, first, extra=self.extra)
        self._unlogged.clear()
        self._last = self.clock()


class _Socket(Protocol):
    def fileno(self) -> int: ...


class _Handler:
    """The loop's exception handler: accept errors of watched sockets to their
    ``Refusals``, everything else to the handler before (or the loop's default)."""

    def __init__(self, before: Callable[[asyncio.AbstractEventLoop, dict[str, Any]], object]
                 | None) -> None:
        self.before = before
        self.watched: dict[int, Refusals] = {}  # listening socket's fd -> its refusals

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        exc, sock = context.get("exception"), context.get("socket")
        if isinstance(exc, OSError) and sock is not None:
            try:
                got = self.watched.get(sock.fileno())
            except (OSError, ValueError):
                got = None
            if got is not None:
                got.refused(reason(exc))
                return
        if self.before is not None:
            self.before(loop, context)
        else:
            loop.default_exception_handler(context)


def watch(sockets: Iterable[_Socket], refusals: Refusals) -> Callable[[], None]:
    """Send the accept errors of these listening sockets (``asyncio.Server.sockets``) to
    ``refusals``, on the running loop; returns the call that stops it (call it before
    the sockets close: a descriptor number is used again)."""
    loop = asyncio.get_running_loop()
    handler = loop.get_exception_handler()
    if not isinstance(handler, _Handler):
        handler = _Handler(handler)
        loop.set_exception_handler(handler)
    fds = [s.fileno() for s in sockets]
    for fd in fds:
        handler.watched[fd] = refusals

    def unwatch() -> None:
        for fd in fds:
            if handler.watched.get(fd) is refusals:
                del handler.watched[fd]
    return unwatch
