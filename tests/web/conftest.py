"""The browser tests run first, so that pytest-xdist gives them to one worker: one
chromium for all of them (``test_web_browser.py``'s ``one_chromium``), not one per
worker that gets one (each start is about 1 CPU-s and 2-4 s of wall).

``--dist worksteal`` hands each worker a contiguous run of the collection and an idle
worker steals from the END of a busy one's run: tests at the very start stay with the
first worker, in order. (``--dist loadgroup`` would keep an ``xdist_group`` together,
but the suite runs ``worksteal``; without xdist the order changes nothing.)"""

from __future__ import annotations

import pytest


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    browser = [item for item in items if "one_chromium" in getattr(item, "fixturenames", ())]
    if browser:
        others = [item for item in items if "one_chromium" not in
                  getattr(item, "fixturenames", ())]
        items[:] = browser + others
