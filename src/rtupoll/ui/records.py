"""Machine-readable records: the JSON and CSV that ``read``, ``poll`` and ``scan`` print.

One record per field reading. ``read --format json`` prints exactly these keys;
``poll`` adds ``status`` and ``time``. A failed reading has ``value`` null and says
why in ``status`` and ``error``: it never carries a stale value.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Mapping
from typing import Any, TextIO

from rtupoll.model.interpret import FieldValue

READ_KEYS = ("device", "profile", "address", "field", "value", "unit", "raw", "severity", "text")
POLL_KEYS = ("time", *READ_KEYS, "status", "error")


def record(device: str, profile: str, address: int, fv: FieldValue) -> dict[str, Any]:
    """One decoded field as a flat dict; enums give their name, flags the active names."""
    return {
        "device": device,
        "profile": profile,
        "address": address,
        "field": fv.field.name,
        "value": fv.value,
        "unit": fv.field.unit,
        "raw": list(fv.raw),
        "severity": fv.severity.value,
        "text": fv.text,
    }


def failed_record(device: str, profile: str, address: int, field: str, unit: str,
                  status: str, error: str) -> dict[str, Any]:
    """A reading that did not happen: no value, and why."""
    return {"device": device, "profile": profile, "address": address, "field": field,
            "value": None, "unit": unit, "raw": None, "severity": "error", "text": "",
            "status": status, "error": error}


def to_json(rec: Mapping[str, Any]) -> str:
    return json.dumps(rec, ensure_ascii=False, separators=(",", ":"))


class CsvWriter:
    """CSV with a fixed header; lists (raw words, flags) are joined with spaces/'|'."""

    def __init__(self, out: TextIO, keys: tuple[str, ...], *, header: bool = True) -> None:
        """``header=False``: the output already has one (appending to a CSV file)."""
        self.out, self.keys = out, keys
        self._writer = csv.DictWriter(out, fieldnames=list(keys), extrasaction="ignore")
        self._header = not header

    def write(self, rec: Mapping[str, Any]) -> None:
        if not self._header:
            self._writer.writeheader()
            self._header = True
        row = {k: _cell(rec.get(k)) for k in self.keys}
        self._writer.writerow(row)


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, list):
        return " ".join(str(x) for x in v) if all(isinstance(x, int) for x in v) \
            else "|".join(str(x) for x in v)
    return str(v)
