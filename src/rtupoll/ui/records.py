"""Machine-readable records: the JSON and CSV that ``read``, ``poll`` and ``scan`` print.

One record per field reading, as ``rtupoll.model.record`` makes it (its keys, a failed
reading's, a value JSON can carry); here it is spelled: strict JSON on one line
(``to_json``: NaN and infinities are null, ``json_safe``), ``poll``'s JSON lines
(``JsonRecords``) and CSV (``CsvWriter``).
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, TextIO

from rtupoll.model.interpret import FieldValue
from rtupoll.model.record import (
    POLL_KEYS,
    failed_record,
    finite,
    iso_time,
    nonfinite_text,
    poll_record,
    record,
)

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.jobs.stats import Reading

def json_safe(obj: Any) -> Any:
    """``obj`` with every NaN/infinity (in dicts, lists and tuples too) replaced by None."""
    if isinstance(obj, float):
        return finite(obj)
    if isinstance(obj, Mapping):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


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


class JsonRecords:
    """``poll``'s JSON lines: ``line(r)`` is ``to_json(reading_record(r)) + "\n"``, byte
    for byte, made with less work for the common record, a value read. What does not
    change from one reading of a field to the next (its device, profile, address, name,
    unit) is encoded once, as JSON text; the value's part (value, raw words, severity,
    text) is encoded again only when the reading differs from the field's last one
    (a value that stays put, as most registers do between two polls, is not formatted
    again). A failed reading, rare, takes the general path. The fragments are keyed by
    what they spell and compared with everything they were made of, so a device renamed
    or moved by a reload, or a field redefined, gets new ones."""

    def __init__(self) -> None:
        self._parts: dict[tuple[str, str, int, str, str], _Parts] = {}

    def line(self, r: Reading) -> str:
        fv = r.value
        if fv is None:
            return to_json(reading_record(r)) + "\n"
        d, f = r.device, r.field
        key = (d.name, d.profile.id, d.address, f.name, f.unit)
        parts = self._parts.get(key)
        if parts is None:
            head = _ENCODE({"device": key[0], "profile": key[1], "address": key[2],
                            "field": key[3]})
            parts = self._parts[key] = _Parts(head[1:-1], f',"unit":{_ENCODE(f.unit)},"raw":[')
        value = fv.value
        if not (fv.raw == parts.raw and fv.field is parts.field and type(value) is parts.kind
                and value == parts.value and fv.sentinel is parts.sentinel
                and fv.severity is parts.severity):
            parts.remember(fv, _value_part(fv, parts.unit))
        return f'{{"time":"{iso_time(r.time)}",{parts.head}{parts.body}'


class _Parts:
    """One field's JSON fragments: its fixed ``head``; the ``body`` of its last reading
    (value to the end), with what that body was made of."""

    __slots__ = ("body", "field", "head", "kind", "raw", "sentinel", "severity", "unit",
                 "value")

    def __init__(self, head: str, unit: str) -> None:
        self.head, self.unit, self.body = head, unit, ""
        self.field: object = None
        self.raw: tuple[int, ...] | None = None
        self.kind: type | None = None
        self.value: Any = None
        self.sentinel: object = None
        self.severity: object = None

    def remember(self, fv: FieldValue, body: str) -> None:
        self.body, self.field, self.raw, self.kind = body, fv.field, fv.raw, type(fv.value)
        self.value, self.sentinel, self.severity = fv.value, fv.sentinel, fv.severity


def _value_part(fv: FieldValue, unit: str) -> str:
    """A value read's record from ``"value"`` to its end, as ``to_json`` spells it."""
    value = fv.output
    kind = type(value)
    if kind is str:
        value_json, text = _ENCODE(value), fv.text
    elif kind is int:
        value_json, text = int.__repr__(value), fv.text  # as json.encoder spells ints
    elif kind is float:
        special = nonfinite_text(value)
        value_json = "null" if special else float.__repr__(value)  # and floats
        text = special or fv.text
    elif value is None:
        value_json, text = "null", fv.text
    else:  # a list of flags, a bool, ...
        value_json, text = to_json(value), fv.text
    try:
        raw = ",".join(map(int.__repr__, fv.raw))
    except TypeError:  # not words (never from a bus): the encoder says it
        raw = _ENCODE(list(fv.raw))[1:-1]
    return (f',"value":{value_json}{unit}{raw}],"severity":"{fv.severity.value}",'
            f'"text":{_ENCODE(text)},"status":"ok","error":""}}\n')


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


class RecordFormat:
    """One format of ``poll``'s records (``ui.record_writer.RecordWriter`` writes them):
    readings in, whole lines out. ``JsonFormat`` and ``CsvFormat`` here,
    ``outputs.influx.InfluxFormat`` for line protocol."""

    def text(self, readings: Sequence[Reading], state: str = "") -> str:
        """The lines of one device cycle (``state``: the device's state after it), or of
        several devices' cycles in a row."""
        raise NotImplementedError

    def restart(self, fresh: bool) -> None:
        """The records go on in another file (SIGHUP); ``fresh``: it is empty."""

    def follow(self, site: Site) -> None:
        """The site polled from now on (a reload): which bus each device is on."""


class JsonFormat(RecordFormat):
    """JSON lines (``JsonRecords``)."""

    def __init__(self) -> None:
        self._line = JsonRecords().line

    def text(self, readings: Sequence[Reading], state: str = "") -> str:
        line = self._line
        return "".join([line(r) for r in readings])


class CsvFormat(RecordFormat):
    """CSV of ``POLL_KEYS``, the header first unless the output has one (``header``)."""

    def __init__(self, *, header: bool = True) -> None:
        self._buf = io.StringIO()
        self._csv = CsvWriter(self._buf, POLL_KEYS, header=header)

    def text(self, readings: Sequence[Reading], state: str = "") -> str:
        for r in readings:
            self._csv.write(reading_record(r))
        text = self._buf.getvalue()
        self._buf.seek(0)
        self._buf.truncate()
        return text

    def restart(self, fresh: bool) -> None:
        """A new file: a header again when it is empty."""
        self._csv = CsvWriter(self._buf, POLL_KEYS, header=fresh)
