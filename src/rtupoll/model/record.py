"""A field reading as a record: the flat dict every machine-readable output starts from
(``read --format json``, ``poll``'s JSON and CSV, ``sniff``, ``decode``), whatever spells it.

One record per field reading. ``read --format json`` prints exactly ``READ_KEYS``;
``poll`` adds ``time``, ``status`` and ``error`` (``POLL_KEYS``). A failed reading has
``value`` null and says why in ``status`` and ``error``: it never carries a stale value.

NaN and infinities are not JSON: a float register holding one gives ``value`` null
and ``text`` ``"NaN"``, ``"+inf"`` or ``"-inf"`` (``finite``, ``nonfinite_text``); every
output (JSON, CSV, MQTT, metrics, Influx) takes a value through ``finite`` for this.
Its time is spelled by ``iso_time``, as logs, MQTT and the sniffer spell a time too.
Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import UTC, datetime
from functools import lru_cache
from typing import Any

from rtupoll.model.interpret import FieldValue

READ_KEYS = ("device", "profile", "address", "field", "value", "unit", "raw", "severity", "text")
POLL_KEYS = ("time", *READ_KEYS, "status", "error")


def finite(value: Any) -> Any:
    """``value``, or None when it is a float NaN or infinity (which JSON cannot carry)."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def nonfinite_text(value: Any) -> str | None:
    """``"NaN"``, ``"+inf"`` or ``"-inf"`` for such a float, else None: the text that
    goes beside a null value so a reader sees why there is none."""
    if not isinstance(value, float) or math.isfinite(value):
        return None
    return "NaN" if math.isnan(value) else ("+inf" if value > 0 else "-inf")


def record(device: str, profile: str, address: int, fv: FieldValue) -> dict[str, Any]:
    """One decoded field as a flat dict; enums give their name, flags the active names."""
    value = fv.output  # null for a sentinel ("not available"); text names it
    special = nonfinite_text(value)
    return {
        "device": device,
        "profile": profile,
        "address": address,
        "field": fv.field.name,
        "value": finite(value),
        "unit": fv.field.unit,
        "raw": list(fv.raw),
        "severity": fv.severity.value,
        "text": special or fv.text,
    }


def failed_record(device: str, profile: str, address: int, field: str, unit: str
                  ) -> dict[str, Any]:
    """A reading that did not happen: no value (why: ``poll_record``'s status and error)."""
    return {"device": device, "profile": profile, "address": address, "field": field,
            "value": None, "unit": unit, "raw": None, "severity": "error", "text": ""}


def poll_record(time: str, rec: Mapping[str, Any], status: str = "ok", error: str = ""
                ) -> dict[str, Any]:
    """``rec`` (``record`` or ``failed_record``) as ``poll`` writes it: POLL_KEYS, in order."""
    return {"time": time, **rec, "status": status, "error": error}


@lru_cache(maxsize=64)  # the readings of one block share their time
def iso_time(t: float) -> str:
    """UTC, millisecond precision, ``Z`` suffix: sorts as text and parses everywhere.

    ``datetime.fromtimestamp(t, UTC).isoformat(timespec="milliseconds")`` with ``Z``,
    character for character (tests/model/test_record.py), without building a datetime per
    stamp: ``t`` is rounded to the microsecond half to even, as ``fromtimestamp`` rounds
    it, and cut to the millisecond, as ``isoformat`` cuts it; the date and time to the
    second are made once a second."""
    fraction, whole = math.modf(t)
    micro = round(fraction * 1e6)
    if micro >= 1_000_000:
        micro, whole = micro - 1_000_000, whole + 1
    elif micro < 0:  # before 1970
        micro, whole = micro + 1_000_000, whole - 1
    return f"{_seconds(int(whole))}.{micro // 1000:03d}Z"


@lru_cache(maxsize=4)
def _seconds(whole: int) -> str:
    return datetime.fromtimestamp(whole, UTC).isoformat(timespec="seconds")[:-6]  # +00:00
