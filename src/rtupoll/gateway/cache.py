"""``--serve-cache SECONDS``: answer a client's read from what the poller read lately.

Every register (or bit) the poller decoded is kept with the time it was read. A
read is answered from here only when every register it asks for was read within
the age limit; otherwise it goes to the line whole. A write through the gateway
forgets what it overwrites. Pure: times are given by the caller.
"""

from __future__ import annotations

from collections.abc import Sequence

from rtupoll.rtu import Table


class ReadCache:
    def __init__(self, max_age: float) -> None:
        self.max_age = max_age
        self._data: dict[tuple[int, Table], dict[int, tuple[int, float]]] = {}
        self.hits = 0

    def put(self, unit: int, table: Table, address: int, words: Sequence[int],
            at: float) -> None:
        regs = self._data.setdefault((unit, table), {})
        for i, w in enumerate(words):
            regs[address + i] = (int(w), at)

    def get(self, unit: int, table: Table, address: int, count: int, now: float
            ) -> tuple[int, ...] | None:
        """All ``count`` values, each read within ``max_age`` of ``now``; else None."""
        regs = self._data.get((unit, table))
        if regs is None:
            return None
        out = []
        for a in range(address, address + count):
            got = regs.get(a)
            if got is None or now - got[1] > self.max_age:
                return None
            out.append(got[0])
        self.hits += 1
        return tuple(out)

    def forget(self, unit: int, table: Table, address: int, count: int) -> None:
        for key in ([k for k in self._data if k[1] is table] if unit == 0 else
                    [(unit, table)]):
            regs = self._data.get(key, {})
            for a in range(address, address + count):
                regs.pop(a, None)
