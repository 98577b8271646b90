"""Fair turns on one RS-485 line between the poller and the gateway's clients.

The line carries one transaction at a time. The poller takes a turn per device cycle
(``BusPoller.turn``); a client takes one per request. When both wait, turns alternate
between the two sides: after a poller cycle the next waiting client request goes,
after a client request the poller's next cycle. Among clients, the one whose last turn
is longest ago goes first, one request each: round-robin among clients that keep
asking, and a client that asks now and then goes ahead of one that hammers the line.
So with the line saturated, the poller keeps at least half of the turns whatever the
clients do, a hammering client cannot starve another client (nor slow one that asks
once in a while by more than a turn), and when the poller is idle (between its
intervals) clients get the whole line.

Turns are handed over in order with futures: nothing here sleeps or reads a clock,
so the rule is tested in virtual time.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import OrderedDict, deque
from collections.abc import AsyncIterator

POLLER = None  # the poller's key; clients are keyed by any hashable (their connection)
REMEMBERED = 256  # clients whose last turn is remembered (one forgotten counts as never)


class Turns:
    def __init__(self) -> None:
        self._busy = False
        self._last_poller = False  # whose turn ended last
        self._poller: deque[asyncio.Future[None]] = deque()
        self._clients: OrderedDict[object, deque[asyncio.Future[None]]] = OrderedDict()
        self._last: OrderedDict[object, int] = OrderedDict()  # client -> its last turn's number
        self.granted = {"poller": 0, "clients": 0}

    @property
    def waiting(self) -> int:
        return len(self._poller) + sum(len(q) for q in self._clients.values())

    @contextlib.asynccontextmanager
    async def turn(self, who: object = POLLER) -> AsyncIterator[None]:
        """Hold the line for one poller cycle (``who`` None) or one client request."""
        if not self._busy and not self.waiting:
            self._grant(who)
        else:
            fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            queue = self._poller if who is POLLER else self._clients.setdefault(who, deque())
            queue.append(fut)
            try:
                await fut
            except asyncio.CancelledError:
                if fut.done() and not fut.cancelled():  # granted as we were cancelled
                    self._release()
                else:
                    self._forget(who, fut)
                raise
        try:
            yield
        finally:
            self._release()

    def _grant(self, who: object) -> None:
        poller = who is POLLER
        self._busy, self._last_poller = True, poller
        self.granted["poller" if poller else "clients"] += 1
        if not poller:
            self._last[who] = self.granted["clients"]
            self._last.move_to_end(who)
            while len(self._last) > REMEMBERED:
                self._last.popitem(last=False)

    def _release(self) -> None:
        self._busy = False
        while True:
            who: object = POLLER
            if self._has_clients() and (self._last_poller or not self._poller):
                who, fut = self._pop_client()
            elif self._poller:
                fut = self._poller.popleft()
            else:
                return
            if not fut.done():  # (a waiter cancelled but not yet forgotten is skipped)
                self._grant(who)
                fut.set_result(None)
                return

    def _has_clients(self) -> bool:
        return any(self._clients.values())

    def _pop_client(self) -> tuple[object, asyncio.Future[None]]:
        """The next client request: of the waiting client whose last turn is longest ago
        (never: first), the oldest one."""
        for key in [k for k, q in self._clients.items() if not q]:
            del self._clients[key]
        if not self._clients:
            raise LookupError("no client waiting")
        key = min(self._clients, key=lambda k: self._last.get(k, 0))
        queue = self._clients[key]
        fut = queue.popleft()
        if not queue:
            del self._clients[key]
        return key, fut

    def _forget(self, who: object, fut: asyncio.Future[None]) -> None:
        queue = self._poller if who is POLLER else self._clients.get(who)
        if queue is not None and fut in queue:
            queue.remove(fut)


class Places:
    """Who may wait for the line: each client's first request has a place of its own,
    always given; a client's further requests take places from ``shared``, all clients
    together, and when none is left the request is refused (the gateway answers 0x0A).
    A client that stops reading its replies keeps what it holds (the gateway stops
    reading from it before it holds more than its own share, ``Gateway``), so it cannot
    take the places others need: a client with nothing waiting always gets its place.

    Pure counting, keyed like ``Turns`` (any hashable): tested without a clock."""

    def __init__(self, shared: int) -> None:
        self.shared = shared
        self.used = 0  # shared places held, all clients
        self._held: dict[object, int] = {}  # places each client holds (its own included)

    def held(self, who: object) -> int:
        return self._held.get(who, 0)

    def take(self, who: object) -> bool:
        """A place for one more request of ``who``; False: none (0x0A)."""
        n = self._held.get(who, 0)
        if n and self.used >= self.shared:
            return False
        if n:
            self.used += 1
        self._held[who] = n + 1
        return True

    def give_back(self, who: object) -> None:
        """One of ``who``'s requests left the queue (answered or dropped)."""
        n = self._held.pop(who, 0)
        if n > 1:
            self.used -= 1
            self._held[who] = n - 1

    @property
    def total(self) -> int:
        return sum(self._held.values())
