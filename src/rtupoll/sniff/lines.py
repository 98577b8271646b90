"""The sniffer's text for scripts and logs: one line per transaction (``--format frames``).

No rich here, so ``rtupoll sniff --format frames`` and ``--format json`` start without it;
the live table is ``sniff.render``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any

from rtupoll.rtu.stream import Transaction
from rtupoll.sniff.model import BusView, describe, function_of

HEADLINE = {"timeout": "NO REPLY", "garbled": "GARBLED REPLY", "exception": "EXCEPTION",
            "orphan": "REPLY TO NO REQUEST", "broken": "BROKEN FRAME", "noise": "STRAY BYTES"}


def clock(t: float) -> str:
    """UTC time of day to the millisecond, as in the JSON records' ``time``."""
    return datetime.fromtimestamp(t, UTC).strftime("%H:%M:%S.%f")[:-3]


def ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.1f} ms"


def frame_line(tx: Transaction, view: BusView, records: Sequence[Mapping[str, Any]]) -> str:
    """One transaction in one line: time, unit, what was asked, reply time, what came back."""
    head = clock(tx.time)
    if tx.status in ("noise", "broken"):
        return f"{head}  {HEADLINE[tx.status]}: {tx.note}"
    if tx.status == "orphan":
        assert tx.reply is not None
        return f"{head}  {HEADLINE['orphan']}: {tx.reply.data.hex(' ')} ({tx.note})"
    assert tx.request is not None
    unit = view.units.get(tx.request.data[0])
    who = unit.name if unit is not None else f"unit {tx.request.data[0]}"
    if tx.status == "broadcast":
        who = "broadcast (unit 0)"
    elif unit is not None and unit.known is not None:
        spec = f"{unit.known.profile.id}@{unit.unit}"
        who = spec if unit.known.name == spec else f"{unit.known.name} ({spec})"
    req = tx.asked
    assert req is not None
    parts = [head, who, describe(req)]
    if tx.reply_time is not None:
        slow = ""
        if unit is not None and unit.known is not None \
                and tx.reply_time > unit.known.profile.limits.timeout:
            slow = f" SLOW (the profile allows {unit.known.profile.limits.timeout:g} s)"
        parts.append(f"reply {ms(tx.reply_time)}{slow}")
    if tx.status in HEADLINE:
        parts.append(f"{HEADLINE[tx.status]}: {tx.note}")
    elif tx.status == "ok":
        ok = [r for r in records if r.get("status") == "ok"]
        if ok and ok[0].get("profile") is None:
            parts.append("values " + " ".join(f"{r['value']:04X}" for r in ok))
        elif ok:
            parts.append(" ".join(f"{r['field']}={r['text']}" + (f" {r['unit']}" if r["unit"]
                                                                  else "") for r in ok))
        elif function_of(req) in (5, 6, 15, 16):
            parts.append("written (echoed)")
    if unit is not None and unit.hints and tx.status == "ok":
        parts.append(f"looks like {unit.hints[0].split(' ')[0]}")
    return "  ".join(parts)
