"""Machine-readable records: the JSON and CSV that ``read``, ``poll`` and ``scan`` print.

One record per field reading. ``read --format json`` prints exactly these keys;
``poll`` adds ``status`` and ``time``. A failed reading has ``value`` null and says
why in ``status`` and ``error``: it never carries a stale value.

NaN and infinities are not JSON: a float register holding one gives ``value`` null
and ``text`` ``"NaN"``, ``"+inf"`` or ``"-inf"``. Every output (JSON, CSV, MQTT,
metrics, Influx) goes through ``finite`` / ``json_safe`` / ``to_json`` for this.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, TextIO

from rtupoll.figures import iso_time
from rtupoll.model.interpret import FieldValue

if TYPE_CHECKING:
    from rtupoll.jobs.stats import Reading

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


def json_safe(obj: Any) -> Any:
    """``obj`` with every NaN/infinity (in dicts, lists and tuples too) replaced by None."""
    if isinstance(obj, float):
        return finite(obj)
    if isinstance(obj, Mapping):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


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


def reading_record(r: Reading) -> dict[str, Any]:
    """A ``poll`` reading (``jobs.stats.Reading``) as its POLL_KEYS record for JSON and CSV."""
    d = r.device
    if r.value is not None:
        return poll_record(iso_time(r.time), record(d.name, d.profile.id, d.address, r.value))
    rec = poll_record(iso_time(r.time), failed_record(
        d.name, d.profile.id, d.address, r.field.name, r.field.unit), r.status.value, r.error)
    if r.status.value == "absent":  # the device's variant lacks it: no failure
        rec["severity"] = "info"
    return rec


def to_json(rec: Any) -> str:
    """Strict JSON on one line: NaN and infinities become null (see ``json_safe``).
    The walk through the record is only done for the rare one that holds such a float."""
    try:
        return _ENCODE(rec)
    except ValueError:  # "Out of range float values are not JSON compliant"
        return _ENCODE(json_safe(rec))


_ENCODE = json.JSONEncoder(ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode


class CsvWriter:
    """CSV with a fixed header; lists (raw words, flags) are joined with spaces/'|'."""

    def __init__(self, out: TextIO, keys: tuple[str, ...], *, header: bool = True) -> None:
        """``header=False``: the output already has one (appending to a CSV file)."""
        import csv  # only the csv format's: the others do not pay for it

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
    v = finite(v)
    if v is None:
        return ""
    if isinstance(v, list):
        return " ".join(str(x) for x in v) if all(isinstance(x, int) for x in v) \
            else "|".join(str(x) for x in v)
    return str(v)
