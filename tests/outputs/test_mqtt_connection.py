"""The broker connection (``outputs.mqtt_connection``): the reconnection backoff.

Losing a real broker and getting it back (one line each way, everything republished)
is in ``test_mqtt_cli.py``; another gateway under the same base in ``test_mqtt_fleet.py``.
"""

from __future__ import annotations

import pytest

from rtupoll.outputs.mqtt_connection import backoff


def test_reconnect_backoff_doubles_to_a_cap() -> None:
    mid = [backoff(n, lambda: 0.5) for n in (1, 2, 3, 4, 12)]
    assert mid == [0.5, 1.0, 2.0, 4.0, 30.0]
    assert backoff(1, lambda: 0.0) == pytest.approx(0.4)
