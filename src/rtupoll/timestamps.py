"""Times as every output writes them: one spelling for records, logs, MQTT and sniff."""

from __future__ import annotations

from datetime import UTC, datetime
from functools import lru_cache


@lru_cache(maxsize=64)  # the readings of one block share their time
def iso_time(t: float) -> str:
    """UTC, millisecond precision, ``Z`` suffix: sorts as text and parses everywhere."""
    stamp = datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")
    return stamp.replace("+00:00", "Z")
