"""InfluxDB line protocol: ``rtupoll poll --format influx``.

One line per block read (the fields a reply carried share its arrival time) and one
status line per device cycle, so telegraf (``inputs.execd``), ``influx write`` and
VictoriaMetrics take the stream as it is::

    rtupoll_reading,address=3,bus=line1,device=air,profile=huiwen-aq co2=1175.0,\
co2_level=1.0,co2_level.text="GOOD" 1763803502517000000
    rtupoll_status,address=3,bus=line1,device=air,profile=huiwen-aq up=1i,ok=15i,failed=0i,\
state="online" 1763803502517000000

(each line broken here only to fit).

**A field key has one type for ever**, whatever device, profile, profile version or
value writes it: InfluxDB (1.x, 2.x and 3.x alike) refuses a whole line whose field
has another type than the one already stored, so a type that depended on the profile
lost whole devices' data. The type is therefore a function of the key alone:

- measurement ``rtupoll_reading``: tags ``address``, ``bus``, ``device``, ``profile``
  (sorted, as InfluxDB prefers). A key without a dot is always a **float**: a number
  (integers too: a profile may scale it tomorrow), an enum's code, a bit field's bits,
  a coil as 1 or 0. A key ending ``.text`` is always a **string**: an enum's name, a
  bit field's active flags joined with ``|``, a text field's text. Profile field names
  are identifiers, so no field can take a ``.text`` key. A failed reading is left
  out: never a stale value, never a zero. NaN and infinities (which line protocol
  cannot carry) are left out too.
- measurement ``rtupoll_status`` (rtupoll's own, fixed fields): ``up`` (1 when the
  cycle got a valid reply), ``ok`` and ``failed`` field counts (integers), ``state``
  and, when something failed, ``status`` and ``error`` (the first failure's).
- timestamps: nanoseconds since the epoch (to the microsecond), from the time the
  reply arrived.

Escaping (the spec's rules): measurement names escape commas and spaces; tag keys,
tag values and field keys escape commas, equals signs and spaces; string field
values are double-quoted with ``"`` and ``\\`` escaped. Line breaks, which no part
of a line may hold, become spaces; a trailing backslash on a key is dropped. Empty tag
values are left out (they are invalid).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

from rtupoll.ui.records import RecordFormat

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.jobs.stats import Reading

MEASUREMENT = "rtupoll_reading"
TEXT = ".text"  # the suffix of every string key (no field name holds a dot)
STATUS_MEASUREMENT = "rtupoll_status"
_MEASUREMENT_ESC = str.maketrans({",": "\\,", " ": "\\ ", "\n": " ", "\r": " "})
_KEY_ESC = str.maketrans({",": "\\,", "=": "\\=", " ": "\\ ", "\n": " ", "\r": " "})
_STRING_ESC = str.maketrans({'"': '\\"', "\\": "\\\\", "\n": " ", "\r": " "})


def measurement(name: str) -> str:
    return name.translate(_MEASUREMENT_ESC)


def key(text: str) -> str:
    """A tag key, tag value or field key. A trailing backslash would escape the
    separator after it, so it is dropped."""
    return text.rstrip("\\").translate(_KEY_ESC)


def string(text: str) -> str:
    return '"' + text.translate(_STRING_ESC) + '"'


def number(value: object) -> str | None:
    """A number, bool or int as a float field value (every number key is a float); None
    when line protocol cannot carry it (NaN, infinities, beyond a float)."""
    if not isinstance(value, (bool, int, float)):
        return None
    try:
        f = float(value)
    except OverflowError:
        return None
    return repr(f) if math.isfinite(f) else None


def tags(reading: Reading, bus: str) -> str:
    d = reading.device
    pairs = {"address": str(d.address), "bus": bus, "device": d.name, "profile": d.profile.id}
    return ",".join(f"{key(k)}={key(v)}" for k, v in sorted(pairs.items()) if v)


def field_values(reading: Reading) -> list[tuple[str, str]]:
    """``(escaped key, value text)`` for one good reading; empty for a failed one."""
    fv = reading.value
    if fv is None:
        return []
    value = fv.output  # None: a sentinel ("not available"), which is no reading
    if value is None:
        return []
    name = fv.field.name
    out: list[tuple[str, str]] = []
    code = fv.code if fv.field.enum or fv.field.flags else None
    if code is not None:
        out.append((key(name), f"{float(code)!r}"))
    elif not isinstance(value, (str, list)):
        text = number(value)
        if text is not None:
            out.append((key(name), text))
    if isinstance(value, list):  # flags: the active names
        out.append((key(name + TEXT), string("|".join(value))))
    elif isinstance(value, str):
        out.append((key(name + TEXT), string(value)))
    return out


def nanoseconds(t: float) -> int:
    """Line protocol's nanoseconds; a float clock carries microseconds, so that is what
    is kept (no invented digits)."""
    return round(t * 1e6) * 1000


def lines(readings: Sequence[Reading], *, bus: str = "", state: str = "") -> list[str]:
    """One device cycle's readings as line protocol (no trailing newlines).

    ``bus`` names the bus tag, ``state`` the device's state after the cycle (both
    optional: without them the tag or field is left out).
    """
    if not readings:
        return []
    tagset = tags(readings[0], bus)
    out: list[str] = []
    group: list[tuple[str, str]] = []
    at: float | None = None
    for r in readings:
        fields = field_values(r)
        if not fields:
            continue
        if at is not None and r.time != at and group:
            out.append(_line(MEASUREMENT, tagset, group, at))
            group = []
        at = r.time
        group.extend(fields)
    if group and at is not None:
        out.append(_line(MEASUREMENT, tagset, group, at))
    out.append(_status_line(readings, tagset, state))
    return out


def _status_line(readings: Sequence[Reading], tagset: str, state: str) -> str:
    good = sum(1 for r in readings if r.ok)
    failed = [r for r in readings if not r.ok and r.status not in ("absent", "skipped")]
    skipped = sum(1 for r in readings if r.status == "skipped")
    up = good > 0 or any(r.status == "exception" for r in readings) or \
        all(r.status == "absent" for r in readings)
    fields = [("up", "1i" if up else "0i"), ("ok", f"{good}i"),
              ("failed", f"{len(failed) + skipped}i")]
    if state:
        fields.append(("state", string(state)))
    if failed:
        fields += [("status", string(failed[0].status)), ("error", string(failed[0].error))]
    return _line(STATUS_MEASUREMENT, tagset, fields, max(r.time for r in readings))


def _line(name: str, tagset: str, fields: Iterable[tuple[str, str]], t: float) -> str:
    head = measurement(name) + ("," + tagset if tagset else "")
    return f"{head} {','.join(f'{k}={v}' for k, v in fields)} {nanoseconds(t)}"


class InfluxFormat(RecordFormat):
    """``poll --format influx``: readings in, whole lines out, each device's ``bus`` tag
    from the site polled (given at the start, ``follow``ed at a reload)."""

    def __init__(self, site: Site | None = None) -> None:
        self._bus: dict[str, str] = {}  # device name -> bus name, this format's own
        if site is not None:
            self.follow(site)

    def follow(self, site: Site) -> None:
        self._bus = {d.name: b.name for b, d in site.devices()}

    def text(self, readings: Sequence[Reading], state: str = "") -> str:
        """Lines for one device cycle (``state``: the device's state after it), or for
        several devices' cycles in a row (``poll --once``)."""
        out: list[str] = []
        start = 0
        for i in range(1, len(readings) + 1):
            if i == len(readings) or readings[i].device.name != readings[start].device.name:
                run = readings[start:i]
                out += lines(run, bus=self._bus.get(run[0].device.name, ""), state=state)
                start = i
        return "".join(line + "\n" for line in out)
