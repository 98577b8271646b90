"""The RTU slave engine: bytes from the master in, reply bytes (or silence) out.

Pure of I/O and clocks, so every rule can be tested with bytes alone; ``server`` adds the
pty/TCP transport and the wire timing.

Two halves:

``Deframer`` finds request frames in a byte stream the way a device's receiver does:
a frame's length follows from its function code (and byte count), and only a frame whose
CRC checks out is taken. Anything before the first good frame is garbage and is dropped
byte by byte, so a stray byte or a half frame never costs the following request.

``Engine`` is the bus behind the port: it counts requests, lets every device that the
unit id reaches answer (none: silence, never exception 04 -- an absent device cannot
answer), and applies the faults due for that request.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rtupoll.rtu import ExceptionCode, crc_ok
from rtupoll.rtu.frames import NOT_A_FRAME, Direction, frame_at
from rtupoll.rtu.functions import FUNCTIONS, WRITE_FUNCTIONS
from rtupoll.rtu.messages import ExceptionReply, Malformed, Request, parse_request
from rtupoll.sim.device import SimDevice, SimDeviceConfig
from rtupoll.sim.faults import SILENT, Fault, FaultSet, mangle

MAX_BUFFER = 512  # bytes kept while looking for a frame; older ones are garbage


def _frame_at(buf: bytes, i: int) -> int | None:
    """Length of a complete, CRC-valid request frame starting at ``buf[i]``, else None."""
    if len(buf) - i < 4:
        return None
    n = frame_at(buf, i, direction=Direction.REQUEST)
    if n > 0:
        return n
    if n == NOT_A_FRAME and buf[i + 1] not in FUNCTIONS:
        # an unknown function: short candidates only (so that it can be refused)
        return next((n for n in range(4, 9) if i + n <= len(buf) and crc_ok(buf[i : i + n])),
                    None)
    return None


class Deframer:
    """Accumulates received bytes and splits off request frames and garbage."""

    def __init__(self) -> None:
        self.buffer = b""

    def feed(self, data: bytes) -> list[tuple[str, bytes]]:
        """New bytes -> ``("frame", bytes)`` and ``("garbage", bytes)`` items, in order."""
        self.buffer += data
        out: list[tuple[str, bytes]] = []
        while self.buffer:
            found = next(((i, n) for i in range(len(self.buffer))
                          if (n := _frame_at(self.buffer, i)) is not None), None)
            if found is None:
                break
            i, n = found
            if i:
                out.append(("garbage", self.buffer[:i]))
            out.append(("frame", self.buffer[i : i + n]))
            self.buffer = self.buffer[i + n :]
        if len(self.buffer) > MAX_BUFFER:
            out.append(("garbage", self.buffer[:-MAX_BUFFER]))
            self.buffer = self.buffer[-MAX_BUFFER:]
        return out

    def flush(self) -> bytes:
        """The line went quiet: whatever is left can no longer become a frame."""
        left, self.buffer = self.buffer, b""
        return left


PAUSE = 0.02  # seconds: a pause fault's default


@dataclass(frozen=True)
class Transmission:
    """One reply to put on the wire: bytes, the device's turnaround and a fault delay."""

    data: bytes
    unit: int  # the device's address when it answered
    turnaround: float  # the profile's (limits.turnaround) or the device's own option
    explicit: bool = False  # the turnaround was set for this device (applies without --baud)
    delay: float = 0.0  # extra, from a slow fault: the reply arrives this much later
    notes: tuple[str, ...] = ()
    pause: float = 0.0  # a pause fault: the reply's second half goes this much later


class Engine:
    """The devices on one simulated bus and the faults that hit them."""

    def __init__(self, devices: Sequence[SimDeviceConfig], faults: Sequence[Fault] = (), *,
                 seed: int = 0, tick: float | None = 1.0, start: float = 0.0) -> None:
        self.devices = [SimDevice(c, seed=seed, tick=tick, start=start) for c in devices]
        self.bus_faults = FaultSet([f for f in faults if f.target is None], seed, "bus")
        self.requests = 0  # valid request frames seen on the bus
        self.replies = 0
        self.why_silent = ""  # why the last request got no reply, for people watching

    def device(self, unit: int) -> SimDevice:
        """The device now at ``unit`` (or first configured there), for tests and pins."""
        for d in self.devices:
            if d.address == unit:
                return d
        for d in self.devices:
            if d.config.address == unit:
                return d
        have = ", ".join(d.name for d in self.devices)
        raise KeyError(f"no simulated device at {unit} (devices: {have})")

    def handle(self, frame: bytes, now: float = 0.0, idle: float = math.inf,
               parity: str | None = None) -> list[Transmission]:
        """One CRC-valid request -> what goes back on the wire (maybe nothing). ``idle``:
        the silence on the line before it began (a device with a ``gap`` fault needs it);
        ``parity``: the parity it was sent at (None: any), only devices at it hear it."""
        self.requests += 1
        unit, fc = frame[0], frame[1]
        broadcast = unit == 0
        self.why_silent = "broadcast: no device replies" if broadcast else ""
        if broadcast and fc not in WRITE_FUNCTIONS:
            return []
        bus_hits = self.bus_faults.due(self.requests, self.requests, 0)
        out: list[Transmission] = []
        targets = [d for d in self.devices if broadcast or d.answers(unit)]
        if not targets:
            self.why_silent = f"no device at {unit}"
        try:
            request: Request | Malformed = parse_request(frame[1:-2], unit=unit)  # CRC: checked
        except Malformed as bad:
            request = bad
        for d in targets:
            if parity is not None and parity != d.profile.serial.parity:  # to it, noise
                self.why_silent = (f"{d.name}: sent at parity {parity}, the device runs at "
                                   f"{d.profile.serial.parity}: parity errors, not a request")
                continue
            if idle + 1e-9 < d.gap:  # the device's receiver was not ready: it never heard it
                self.why_silent = (f"{d.name}: gap: the request came {idle * 1000:.1f} ms after "
                                   f"the last byte on the line; it needs {d.gap * 1000:g} ms")
                continue
            d.requests += 1
            d.catch_up(now)
            lose = d.profile.limits.lost_after_powerup or 3
            hits = [*d.faults.due(self.requests, d.requests, lose),
                    *(f for f in bus_hits if f.kind != "lose-first"),
                    *(f for f in self.bus_faults.faults if f.kind == "lose-first"
                      and d.requests <= (int(f.arg) if f.arg is not None else lose))]
            silent = [str(f) for f in hits if f.kind in SILENT]
            if silent:  # dead, or still starting up: the request is not even processed
                self.why_silent = f"{d.name}: {', '.join(silent)}"
                continue
            exc = next((f for f in hits if f.kind == "exception"), None)
            at = d.address
            if exc is not None:
                code = int(exc.arg) if exc.arg is not None else ExceptionCode.DEVICE_FAILURE
                reply: bytes | None = ExceptionReply(unit, fc, code).frame()
            else:
                reply = d.handle(request)
            if reply is None or broadcast:
                if not broadcast:
                    self.why_silent = f"{d.name} does not answer this request"
                continue
            data, delay, notes = mangle(reply, hits, at, 2 * d.profile.limits.timeout)
            if exc is not None:
                notes.insert(0, f"exception {reply[2]}")
            ta = d.config.turnaround
            pause = next(((f.arg if f.arg is not None else PAUSE) for f in hits
                          if f.kind == "pause"), 0.0)
            if pause:
                notes.append(f"pause {pause * 1000:g} ms")
            out.append(Transmission(data, at, d.profile.limits.turnaround if ta is None else ta,
                                    ta is not None, delay, tuple(notes), pause))
        self.replies += len(out)
        return out
