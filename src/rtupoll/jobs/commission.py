"""Giving a device a new address: refuse what is unsafe, write, then prove it moved.

Every new sensor ships at the same address, so commissioning is a chore done twenty
times in a row, often by script. Each change follows the same steps, and each step
exists because skipping it has bitten someone:

1. refuse before sending: no documented method (say what the manual says instead),
   a reserved or out-of-range address, or an address something already answers at
   (two devices at one address corrupt each other's replies);
2. the device must answer at its current address and, when asked, prove its identity
   (a serial number), so a script never readdresses the wrong sensor;
3. write the address register the way the profile says (FC06, or FC16 with a
   read-modify-write when the address is one byte of a shared register);
4. verify: it answers at the new address and no longer at the old one. A missing or
   malformed reply to the write itself means nothing (the Huiwen manual's FC06
   reply is not an echo; many devices answer from the new address or not at all):
   verification decides.

A change whose device already answers at the new address (and not at the old one,
or with a matching identity) is "already done", which makes plans safe to re-run.
"""

from __future__ import annotations

import enum
from collections.abc import Awaitable, Callable, Collection
from dataclasses import dataclass
from typing import TYPE_CHECKING

from rtupoll.errors import (
    DeviceException,
    DeviceTimeout,
    FrameError,
    Interrupted,
    PortError,
    RefusedError,
    RtupollError,
    VerificationError,
)
from rtupoll.jobs.device import Timing
from rtupoll.jobs.device import timing as device_timing
from rtupoll.jobs.writes import WriteOp, write
from rtupoll.model.addressing import Change, address_field, refuse
from rtupoll.model.codec import DataType
from rtupoll.model.interpret import field_words, interpret
from rtupoll.model.profile import Field, Profile
from rtupoll.rtu.functions import WRITE_DATA_AT
from rtupoll.rtu.messages import ReadRequest, WriteMultiple, WriteSingle

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike

VERIFY_ATTEMPTS = 3  # a device may take a moment to start answering at its new address
VERIFY_PAUSE = 0.05  # seconds between attempts


class Presence(str, enum.Enum):
    """What answers at an address, judged by reading the profile's address register."""

    SILENT = "silent"  # nothing answers
    SAME = "same"  # a device whose address register holds this very address
    OTHER = "other"  # something answers, but not like this profile's device would


class Status(str, enum.Enum):
    CHANGED = "changed"
    DONE = "already done"
    FAILED = "failed"
    UNVERIFIED = "written, unverified"  # interrupted after the write went out
    NOT_RUN = "not run"


INTERRUPTED = Interrupted.exit_code  # the exit code of a row an interruption cut short


class Absent(DeviceTimeout):
    """Nothing answers at a change's old address (for a shared one: the next sensor is
    not connected yet)."""


class PlanInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during a plan: every row's state, reported before it ends."""

    def __init__(self, results: list[Result]) -> None:
        super().__init__("interrupted")
        self.results = results


@dataclass(frozen=True)
class Result:
    change: Change
    status: Status
    detail: str
    error: RtupollError | None = None

    def record(self, row: int) -> dict[str, object]:
        """The JSON report line of this row."""
        c = self.change
        return {"row": row, "profile": c.profile.id, "address": c.old, "new": c.new,
                "status": self.status.value, "detail": self.detail,
                "exit_code": self.error.exit_code if self.error
                else INTERRUPTED if self.status is Status.UNVERIFIED
                else None if self.status is Status.NOT_RUN else 0}


def dry_run(change: Change) -> list[tuple[str, str]]:
    """The frames a change would send, as (hex, why); ``??`` marks bytes read first."""
    f = refuse(change)
    p, old, new = change.profile, change.old, change.new
    read_old = ReadRequest(old, f.table.read_function, f.address, f.words).frame()
    out = [(_hex(ReadRequest(new, f.table.read_function, f.address, f.words).frame()),
            f"probe {new}: must be silent (nothing may answer there yet)"),
           (_hex(read_old), f"read {f.name} at {old}: the device must answer")]
    if change.check:
        cf = p.field(change.check[0])
        out.append((_hex(ReadRequest(old, cf.table.read_function, cf.address, cf.words).frame()),
                    f"identity: {cf.name} must read {change.check[1]}"))
    words = field_words(f, new, (0,))
    function = p.set_address.function
    unknown: set[int] = set()
    if f.layout.type in (DataType.U8, DataType.I8):
        out.append((_hex(read_old), f"read {f.name}'s register to keep its other byte"))
        at = WRITE_DATA_AT[function]  # the register's high byte; its low byte follows
        unknown = {at if f.layout.byte == "low" else at + 1}  # the byte kept, read first
    if function == 6:
        frame = WriteSingle(old, 6, f.address, words[0]).frame()
    else:
        frame = WriteMultiple(old, 16, f.address, tuple(words)).frame()
    reply = {"echo": "an echo", "none": "no reply", "malformed": "a malformed reply",
             "any": "any reply, or none"}[p.set_address.reply]
    crc = {len(frame) - 2, len(frame) - 1} if unknown else set()
    out.append((_hex(frame, unknown | crc),
                f"write {new} to {f.name} with FC{p.set_address.function:02d} "
                f"(expects {reply}; verification decides)"))
    out.append((_hex(ReadRequest(new, f.table.read_function, f.address, f.words).frame()),
                f"verify: {f.name} at {new} must read {new}"))
    if old != p.addresses.any:
        out.append((_hex(read_old), f"verify: {old} must be silent now"))
    return out


class Commissioner:
    """Runs address changes on one bus, with per-profile timing (or the user's override)."""

    def __init__(self, bus: BusLike, *, timeout: float | None = None, retries: int | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        self.bus, self.timeout, self.retries = bus, timeout, retries
        self.log = log or (lambda _msg: None)
        self.sent: Change | None = None  # a change whose write may be out, not yet verified

    def timing(self, profile: Profile) -> Timing:
        return device_timing(profile, self.timeout, self.retries)

    async def presence(self, profile: Profile, unit: int) -> Presence:
        f = address_field(profile)
        t = self.timing(profile)
        try:
            words = (await self.bus.read(unit, f.table, f.address, f.words,
                                         timeout=t.timeout, retries=t.retries)).values
        except DeviceTimeout:
            return Presence.SILENT
        except (FrameError, DeviceException):  # an exception reply or garbage: someone is there
            return Presence.OTHER
        value = interpret(f, words).value
        return Presence.SAME if value == unit or unit == profile.addresses.any else Presence.OTHER

    async def identity(self, change: Change, unit: int) -> str | None:
        """Why the device at ``unit`` is not the one the change names (None: it is)."""
        if not change.check:
            return None
        name, want = change.check
        f = change.profile.field(name)
        t = self.timing(change.profile)
        words = (await self.bus.read(unit, f.table, f.address, f.words, timeout=t.timeout,
                                     retries=t.retries)).values
        got = interpret(f, words)
        if got.text == want or _same_number(got.value, want):
            return None
        return f"{name} reads {got.text!r}, expected {want!r}"

    async def apply(self, change: Change) -> Result:
        """Make the change, or recognise it as already done; raises on refusal or failure."""
        field = refuse(change)
        p, old, new = change.profile, change.old, change.new
        at_new = await self.presence(p, new)
        if at_new is Presence.SAME and await self.identity(change, new) is None and (
                change.check or old == p.addresses.any or change.shared
                or await self.presence(p, old) is Presence.SILENT):
            return Result(change, Status.DONE, f"already done: answers at {new}"
                          + (f", {change.check[0]} matches" if change.check else "")
                          + (f", silent at {old}" if not change.check else ""))
        if at_new is not Presence.SILENT:
            raise RefusedError(f"{change.label}: address {new} is taken: a device already "
                               "answers there (pick another; 'rtupoll scan' lists the bus)")
        at_old = await self.presence(p, old)
        if at_old is Presence.SILENT and change.shared:
            raise Absent(f"{change.label}: no sensor answers at {old}: connect the next one "
                         f"(alone at {old}) and run the plan again; the rows done are "
                         "verified and skipped")
        if at_old is Presence.SILENT:
            raise Absent(f"{change.label}: no device answers at {old} "
                         "(check wiring, power and serial settings)")
        if at_old is Presence.OTHER:
            raise RefusedError(f"{change.label}: the device at {old} does not look like a "
                               f"{p.id} ({field.name} does not read {old})")
        wrong = await self.identity(change, old)
        if wrong:
            raise RefusedError(f"{change.label}: not the device this change is for: {wrong}")
        self.sent = change  # from here on, an interruption leaves it unverified
        reply = await self._write(p, field, old, new)
        self.log(f"{change.label}: written ({reply}); verifying")
        await self._verify(change)
        self.sent = None
        return Result(change, Status.CHANGED,
                      f"changed: answers at {new}"
                      + ("" if old == p.addresses.any else f", silent at {old}")
                      + f" (write reply: {reply})")

    async def _write(self, p: Profile, f: Field, old: int, new: int) -> str:
        """Write the new address (read-modify-write for a shared register); what came back."""
        op = WriteOp(f, new, field_words(f, new, (0,)), p.set_address.function)
        try:
            _, echoed = await write(self.bus, old, op, self.timing(p), reply=p.set_address.reply)
        except DeviceTimeout:
            return "none"
        except FrameError:
            return "malformed"
        return "echo" if echoed else "none or not an echo"

    async def _verify(self, change: Change) -> None:
        import asyncio  # loaded by then (a coroutine runs in a loop): a dry run never is

        p, old, new = change.profile, change.old, change.new
        at_new = Presence.SILENT
        for attempt in range(VERIFY_ATTEMPTS):
            if attempt:
                await asyncio.sleep(VERIFY_PAUSE)
            at_new = await self.presence(p, new)
            if at_new is Presence.SAME:
                break
        if at_new is not Presence.SAME:
            at_old = await self.presence(p, old)
            if at_old is Presence.SAME:
                raise VerificationError(f"{change.label}: the device still answers at {old}; "
                                        "the new address did not take effect")
            raise VerificationError(f"{change.label}: the device answers at neither {old} "
                                    f"nor {new} (power-cycle it and check both)")
        if old != p.addresses.any and await self.presence(p, old) is not Presence.SILENT:
            raise VerificationError(f"{change.label}: the device answers at {new}, but "
                                    f"something still answers at {old}")

    async def next_free(self, profile: Profile, start: int, skip: set[int]) -> int:
        """The first address from ``start`` that this device may take and nothing answers at."""
        a = profile.addresses
        for candidate in range(max(start, a.lo), a.hi + 1):
            if candidate in skip or a.check(candidate):
                continue
            if await self.presence(profile, candidate) is Presence.SILENT:
                return candidate
            self.log(f"{candidate} is taken; trying the next address")
        raise RefusedError(f"no free address left in {max(start, a.lo)}..{a.hi}")


async def run_plan(commissioner: Commissioner, changes: list[Change],
                   on_result: Callable[[Result], None] | None = None,
                   next_sensor: Callable[[Change, bool], Awaitable[bool]] | None = None
                   ) -> list[Result]:
    """Run changes in order; stop at the first failure; the rest are reported not run.

    A shared row (sensors that all come at one address) whose device is not there yet
    waits for ``next_sensor(change, again)`` (a person connecting it: True to try the row,
    False to stop; ``again`` when it was tried already), or without one fails saying to
    connect it and run the plan again.

    Interrupted (Ctrl-C, SIGTERM), every row is still reported: the one in progress as
    ``written, unverified`` if its write may have gone out, else ``not run``, like the
    rest; then ``PlanInterrupted`` (a KeyboardInterrupt) carries the results.
    """
    import asyncio  # loaded by then (a coroutine runs in a loop): a dry run never is

    results: list[Result] = []
    failed = interrupted = stopped = False
    for change in changes:
        if interrupted:
            result = Result(change, Status.NOT_RUN, "not attempted (interrupted)")
        elif failed:
            result = Result(change, Status.NOT_RUN, "not attempted (an earlier row failed)")
        elif stopped:
            result = Result(change, Status.NOT_RUN, "not attempted (stopped)")
        else:
            commissioner.sent = None
            try:
                result = await _apply(commissioner, change, next_sensor)
                stopped = result.status is Status.NOT_RUN
            except RtupollError as exc:
                failed = True
                why = cut_off(change, exc) if isinstance(exc, PortError) and \
                    commissioner.sent is change else str(exc)
                result = Result(change, Status.FAILED, why.removeprefix(f"{change.label}: "),
                                exc)
            except (asyncio.CancelledError, KeyboardInterrupt):
                interrupted = True
                result = cut_short(change, commissioner.sent is change)
        results.append(result)
        if on_result:
            on_result(result)
    if interrupted:
        raise PlanInterrupted(results)
    return results


async def _apply(commissioner: Commissioner, change: Change,
                 next_sensor: Callable[[Change, bool], Awaitable[bool]] | None) -> Result:
    again = False
    while True:
        try:
            return await commissioner.apply(change)
        except Absent:
            if not (change.shared and next_sensor):
                raise
        if not await next_sensor(change, again):
            return Result(change, Status.NOT_RUN, "not attempted (stopped)")
        again = True


def cut_short(change: Change, sent: bool, again: str = "run the plan again") -> Result:
    """What an interruption left: ``sent``, the write may be out (the device may be at
    either address), else nothing was written. ``again``: what finishes the job."""
    if sent:
        return Result(change, Status.UNVERIFIED,
                      f"interrupted after the write: the device may be at {change.new} or "
                      f"still at {change.old}; {again} to check both and finish")
    return Result(change, Status.NOT_RUN, "interrupted before anything was written")


def cut_off(change: Change, exc: PortError, again: str = "run the plan again") -> str:
    """A port lost once the write may be out: where the device may be now."""
    return (f"{exc}: the write may have gone out, so the device may be at {change.new} or "
            f"still at {change.old}; {again} once the port is back to check both and finish")


def _same_number(value: object, text: str) -> bool:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return float(text) == float(value)
    except ValueError:
        return False


def _hex(frame: bytes, unknown: Collection[int] = ()) -> str:
    return " ".join("??" if i in unknown else f"{b:02X}" for i, b in enumerate(frame))
