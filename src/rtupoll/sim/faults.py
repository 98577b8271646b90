"""Fault injection: what can go wrong between a request and its reply, and when.

Real RS-485 buses fail in a handful of ways that a client must survive (see "A shared
bus" in the design notes): a device that never answers, one that answers too late, a
corrupted or cut-off reply, a stray byte from a transceiver switching direction, a reply
from another id, an exception, and a board that drops its first requests after power-up.
Each is a ``Fault`` parsed from one short spec, so the same text works on the command
line (``--fault``), in a scenario file and in tests::

    [ADDRESS:]KIND[=ARG][@WHEN]

    3:dead              device 3 never answers
    slow=1.5@2,5-7      every device answers 1.5 s late to bus requests 2 and 5..7
    0xFE:crc@10%        one in ten replies of the device at 0xFE has a bad CRC
    3:gap=0.05          device 3 hears a request only after 50 ms of silence on the line
    lose-first          every device drops its first limits.lost_after_powerup requests

WHEN is a rate (``0.1`` or ``10%``: drawn from the seeded generator, so a seed replays the
same faults; the first hit comes within the first 1/rate requests, so ``crc@20%`` shows
in the first five, not whenever the dice say) or a schedule of request numbers (``3``,
``2,4``, ``5-7``, ``10-`` for "from 10 on"); without it the fault hits every request.
A device's faults count the requests that device received; bus-wide faults count every
valid request on the bus.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass

from rtupoll.errors import FaultSpecError
from rtupoll.rtu import with_crc

# kind -> what it does to the reply (also the help text of --fault)
KINDS: dict[str, str] = {
    "dead": "never answers",
    "slow": "answers ARG seconds late (default: twice the profile's timeout)",
    "crc": "the reply's CRC is wrong",
    "stray": "a stray byte ARG (default 0x00) goes out before the reply",
    "truncate": "only the first ARG bytes of the reply go out (default: half)",
    "wrong-id": "the reply carries id ARG (default: the next address) instead",
    "wrong-id-first": "a copy of the reply from id ARG, then the right reply, back to back",
    "exception": "an exception reply with code ARG (default 4) instead of the answer",
    "lose-first": "the first ARG requests after start-up are lost (default: the profile's "
                  "limits.lost_after_powerup, or 3)",
    "hole": "register ARG (wire address) is an undocumented hole: any read over it gets "
            "exception 02, even inside a gap the profile bridges",
    "shift": "register ARG is an undocumented hole the device silently skips: a block read "
             "over it returns the following registers shifted down, padded with 0",
    "pause": "the reply stops half-way for ARG seconds (default 0.02) before the rest: a "
             "device or gateway that breaks its frames",
    "gap": "the device needs ARG seconds of silence on the line before a request (an idle "
           "gap, the 'T delay' of some meters): a request sooner after the last byte on the "
           "line, any device's, is not heard",
}
QUIRKS = ("hole", "shift", "gap")  # properties of the device, not of one request
SILENT = ("dead", "lose-first")
_FLOAT_ARG = {"slow", "gap", "pause"}
_INT_ARG = {"stray": (0, 255), "truncate": (1, 255), "wrong-id": (0, 255),
            "wrong-id-first": (0, 255), "exception": (1, 255), "lose-first": (0, 1000),
            "hole": (0, 0xFFFF), "shift": (0, 0xFFFF)}


@dataclass(frozen=True)
class Fault:
    kind: str
    target: int | None = None  # device address it was given for; None: bus-wide
    arg: float | None = None
    rate: float | None = None  # probability per request; None: see schedule
    schedule: tuple[tuple[int, int | None], ...] = ()  # request number ranges; () + no rate: all
    text: str = ""

    @property
    def per_device(self) -> bool:
        """Counts the device's own requests (lose-first always does: power-up is per board)."""
        return self.target is not None or self.kind == "lose-first"

    def scheduled(self, n: int) -> bool:
        return any(lo <= n and (hi is None or n <= hi) for lo, hi in self.schedule)

    def __str__(self) -> str:
        return self.text or self.kind


def _number(text: str, what: str, spec: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise FaultSpecError(f"fault {spec!r}: {what} {text!r} is not a whole number") from None


def parse_fault(spec: str) -> Fault:
    """``[ADDRESS:]KIND[=ARG][@WHEN]`` -> Fault (see the module docstring)."""
    text = spec.strip()
    rest, at, when = text.partition("@")
    if at and not when.strip():
        raise FaultSpecError(f"fault {spec!r}: nothing after '@' (a rate like 10% or "
                             "request numbers like 3, 2,4 or 5-)")
    target: int | None = None
    if ":" in rest:
        addr, _, rest = rest.partition(":")
        target = _number(addr, "address", spec)
        if not 0 < target <= 255:
            raise FaultSpecError(f"fault {spec!r}: address {target} is outside 1..255")
    kind, has_arg, arg_text = rest.partition("=")
    kind = kind.strip().lower()
    if kind not in KINDS:
        from rtupoll.model.names import close_names

        hint = close_names(kind, KINDS)
        raise FaultSpecError(f"fault {spec!r}: unknown kind {kind!r}"
                             + (f" (did you mean {hint[0]!r}?)" if hint else "")
                             + f"; kinds: {', '.join(KINDS)}")
    arg: float | None = None
    if has_arg:
        if kind in _FLOAT_ARG:
            try:
                arg = float(arg_text)
            except ValueError:
                raise FaultSpecError(f"fault {spec!r}: {arg_text!r} is not seconds") from None
            if not 0 <= arg <= 60:
                raise FaultSpecError(f"fault {spec!r}: {arg:g} s is outside 0..60 s")
        elif kind in _INT_ARG:
            lo, hi = _INT_ARG[kind]
            arg = _number(arg_text, "argument", spec)
            if not lo <= arg <= hi:
                raise FaultSpecError(f"fault {spec!r}: {int(arg)} is outside {lo}..{hi}")
        else:
            raise FaultSpecError(f"fault {spec!r}: {kind} takes no argument")
    rate, schedule = _when(when, spec) if when else (None, ())
    if kind in QUIRKS and (target is None or arg is None or when):
        what = "seconds" if kind == "gap" else "REGISTER"
        raise FaultSpecError(f"fault {spec!r}: {kind} is a property of one device: "
                             f"ADDRESS:{kind}={what}, without @WHEN")
    if kind == "lose-first" and when:
        raise FaultSpecError(f"fault {spec!r}: lose-first has its own schedule "
                             "(the first N requests); give N as lose-first=N")
    return Fault(kind, target, arg, rate, schedule, text)


def _when(when: str, spec: str) -> tuple[float | None, tuple[tuple[int, int | None], ...]]:
    w = when.strip()
    if w.endswith("%") or "." in w:
        try:
            rate = float(w[:-1]) / 100 if w.endswith("%") else float(w)
        except ValueError:
            raise FaultSpecError(f"fault {spec!r}: rate {w!r} is not a number") from None
        if not 0 <= rate <= 1:
            raise FaultSpecError(f"fault {spec!r}: rate {w!r} is outside 0..1 (0%..100%)")
        return rate, ()
    ranges: list[tuple[int, int | None]] = []
    for item in w.split(","):
        lo_text, dash, hi_text = item.strip().partition("-")
        lo = _number(lo_text, "request number", spec)
        hi = (_number(hi_text, "request number", spec) if hi_text else None) if dash else lo
        if lo < 1 or (hi is not None and hi < lo):
            raise FaultSpecError(f"fault {spec!r}: {item!r} is not a request number or range "
                                 "(requests count from 1)")
        ranges.append((lo, hi))
    return None, tuple(ranges)


class FaultSet:
    """Faults with their own seeded generators, deciding which hit a given request."""

    def __init__(self, faults: Sequence[Fault], seed: int, salt: str) -> None:
        self.faults = tuple(faults)
        self._rngs = [random.Random(f"{seed}:{salt}:{i}:{f.text}") for i, f in enumerate(faults)]
        self._hit = [False] * len(self.faults)  # a rated fault has hit at least once

    def due(self, bus_n: int, device_n: int, lose_first: int) -> list[Fault]:
        """The faults that hit this request. Every rated fault draws every time, so one
        fault's outcome never depends on whether another was configured."""
        hits: list[Fault] = []
        for i, (fault, rng) in enumerate(zip(self.faults, self._rngs, strict=True)):
            n = device_n if fault.per_device else bus_n
            if fault.kind == "lose-first":
                limit = int(fault.arg) if fault.arg is not None else lose_first
                hit = n <= limit
            elif fault.rate is not None:
                hit = rng.random() < fault.rate
                if fault.rate and not self._hit[i] and n >= math.ceil(1 / fault.rate):
                    hit = True  # at the latest by request 1/rate: seen in the first seconds
                self._hit[i] = self._hit[i] or hit
            else:
                hit = fault.scheduled(n) if fault.schedule else True
            if hit:
                hits.append(fault)
        return hits


def readdress(frame: bytes, unit: int) -> bytes:
    """The same reply as if sent by ``unit`` (a valid frame with its own CRC)."""
    return with_crc(bytes([unit]) + frame[1:-2])


def mangle(reply: bytes, hits: Sequence[Fault], unit: int, slow_default: float
           ) -> tuple[bytes, float, list[str]]:
    """Apply the reply-changing faults in a fixed order; returns bytes, extra delay, notes."""
    data, delay, notes = reply, 0.0, []
    kinds = {f.kind: f for f in hits}
    if "wrong-id" in kinds:
        other = _other_id(kinds["wrong-id"], unit)
        data = readdress(data, other)
        notes.append(f"wrong-id {other}")
    if "wrong-id-first" in kinds:
        other = _other_id(kinds["wrong-id-first"], unit)
        data = readdress(data, other) + data
        notes.append(f"wrong-id-first {other}")
    if "crc" in kinds:
        data = data[:-2] + bytes([data[-2] ^ 0xFF, data[-1] ^ 0xFF])
        notes.append("crc")
    if "truncate" in kinds:
        arg = kinds["truncate"].arg
        keep = int(arg) if arg is not None else max(1, len(data) // 2)
        data = data[:keep]
        notes.append(f"truncate {keep}")
    if "stray" in kinds:
        arg = kinds["stray"].arg
        data = bytes([int(arg) if arg is not None else 0]) + data
        notes.append(f"stray 0x{data[0]:02X}")
    if "slow" in kinds:
        arg = kinds["slow"].arg
        delay = arg if arg is not None else slow_default
        notes.append(f"slow {delay:g}s")
    return data, delay, notes


def _other_id(fault: Fault, unit: int) -> int:
    return int(fault.arg) if fault.arg is not None else unit % 247 + 1
