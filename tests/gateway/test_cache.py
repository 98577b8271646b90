"""The gateway's read cache (rtupoll.gateway.cache)."""

from __future__ import annotations

from rtupoll.gateway.cache import ReadCache
from rtupoll.rtu import Table


def test_cache_answers_only_what_it_covers_within_age() -> None:
    c = ReadCache(2.0)
    c.put(3, Table.INPUT, 100, [1, 2, 3], at=10.0)
    c.put(3, Table.INPUT, 103, [4], at=11.0)
    assert c.get(3, Table.INPUT, 101, 3, now=11.5) == (2, 3, 4)
    assert c.get(3, Table.INPUT, 101, 4, now=11.5) is None  # 104 was never read
    assert c.get(3, Table.HOLDING, 100, 1, now=11.5) is None
    assert c.get(3, Table.INPUT, 100, 1, now=12.5) is None  # too old
    c.forget(3, Table.INPUT, 102, 1)
    assert c.get(3, Table.INPUT, 101, 2, now=11.0) is None
