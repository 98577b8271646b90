"""A profile at an address on a bus: the one read job, and probing the variant.

The glue between the pure layers (profile, planner, reading) and the bus. Every read of
a device's fields goes through here: ``rtupoll read`` and MQTT ``get`` whole
(``read_fields``), ``poll``'s cycle block by block (``read_block``, one timed transaction
each, its values and its evidence as one value, ``BlockValues``, then the same rule for a
refused block, ``after_refusal``). What the
device taught earlier (its variant, the holes it refused: ``jobs.holes``) is an input,
and what a read gives (values, why the other fields have none, holes found) comes back
as one value, ``Read``. Timeouts and retries default to the profile's ``limits``,
because the device's manual, not the caller, knows how slow it is and whether it drops
the first request after power-up. Fields the device's variant does not have (``since``
above it) are left out of the plan rather than read into an exception reply.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import field
from typing import TYPE_CHECKING

from rtupoll.errors import DeviceException, FrameError
from rtupoll.frozen import frozen, mutable
from rtupoll.io.interface import BusLike
from rtupoll.model.interpret import FieldValue
from rtupoll.model.planner import Block, decode_block, plan
from rtupoll.model.profile import Field, Limits, Profile
from rtupoll.model.scaling import Unscaled, scale_values
from rtupoll.rtu import ExceptionCode, exception_name

if TYPE_CHECKING:
    from rtupoll.jobs.holes import Register
    from rtupoll.rtu.transaction import Evidence

__all__ = ["BlockRead", "BlockValues", "Read", "Timing", "Variant", "needs_variant",
           "probe_variant", "read_block", "read_fields", "read_planned", "timing"]


@frozen
class Timing:
    timeout: float
    retries: int


def timing(profile: Profile | None, timeout: float | None = None, retries: int | None = None
           ) -> Timing:
    """The caller's overrides, else the profile's ``limits.timeout`` / ``limits.retries``
    (with no profile, the defaults a profile gets when it says nothing)."""
    limits = profile.limits if profile is not None else Limits()
    return Timing(limits.timeout if timeout is None else timeout,
                  limits.retries if retries is None else retries)


@mutable(slots=True)  # made per transaction: plain, not frozen (CPU)
class BlockValues:
    """One planned read, decoded, and its transaction's evidence (``rtu.transaction.
    Evidence``: what the poller's timing learns from, ``jobs.timeouts``)."""

    values: list[FieldValue]
    evidence: Evidence


Decode = Callable[[Block, Sequence[int]], list[FieldValue]]  # model.planner.decode_block's


async def read_block(bus: BusLike, unit: int, block: Block, *, timeout: float,
                     retries: int, patience: float = 0.0,
                     idle_gap: float | None = None,
                     decode: Decode = decode_block) -> BlockValues:
    """One planned read, decoded (by ``decode``: ``decode_block``, or one that remembers,
    the poller's): one transaction (``patience``, ``idle_gap``: ``BusLike.read``'s). Bus
    errors propagate, each with its evidence (``BusError.evidence``)."""
    got = await bus.read(unit, block.table, block.address, block.count,
                         timeout=timeout, retries=retries, patience=patience,
                         idle_gap=idle_gap)
    return BlockValues(decode(block, got.values), got.evidence)


@frozen
class BlockRead:
    """What one planned block gave: the values read, the fields the device refuses (with
    the exception), and the registers bisection found it refuses (``holes``: none when the
    block read whole)."""

    values: list[FieldValue]
    refused: tuple[tuple[Field, DeviceException], ...] = ()
    holes: frozenset[Register] = frozenset()


async def after_refusal(bus: BusLike, unit: int, block: Block, exc: DeviceException, *,
                        timeout: float, retries: int) -> BlockRead | None:
    """``block`` was refused with ``exc``: with exception 02 (illegal data address) over a
    gap or several fields, what the device refuses is found by bisection (``jobs.holes``)
    and every other field read; None when nothing of the block reads (the exception stands
    for all its fields). Timeouts and garbled replies during the bisection propagate."""
    from rtupoll.jobs.holes import bisect, gaps  # here: a read that is not refused needs none

    if exc.code != ExceptionCode.ILLEGAL_ADDRESS or not (gaps(block) or len(block.fields) > 1):
        return None
    found = await bisect(bus, unit, block, timeout=timeout, retries=retries)
    return None if found is None else BlockRead(found.values, found.refused, found.holes)


async def read_planned(bus: BusLike, unit: int, block: Block, *, timeout: float,
                       retries: int) -> BlockRead:
    """``block`` read; refused: ``after_refusal``, else each field refused with the
    exception. A timeout or a garbled reply propagates."""
    try:
        return BlockRead((await read_block(bus, unit, block, timeout=timeout,
                                           retries=retries)).values)
    except DeviceException as exc:
        found = await after_refusal(bus, unit, block, exc, timeout=timeout, retries=retries)
        return found or BlockRead([], tuple((f, exc) for f in block.fields))


def needs_variant(profile: Profile, fields: Sequence[Field]) -> bool:
    """Whether reading ``fields`` needs the device's variant first: some of them exist only
    in some generations of the map (IRNET data structure 1)."""
    return profile.variant is not None and any(f.since for f in fields)


@frozen
class Read:
    """What reading some fields of a device gave, as one value.

    ``values``: the fields that read, scaled (``scale_by``), in the order asked (a field
    asked twice comes back once); ``missing``: why each other field has no value (not in
    the device's variant, refused, not scaled); ``variant``: the one the read planned for
    (probed, or as given); ``holes``: per refused block, the registers bisection found the
    device refuses (for the caller to learn, ``jobs.holes.HoleMemory``)."""

    unit: int
    values: tuple[FieldValue, ...]
    missing: Mapping[str, str] = field(default_factory=dict)
    refused: tuple[tuple[Field, DeviceException], ...] = ()
    unscaled: tuple[Unscaled, ...] = ()
    variant: int | None = None
    holes: tuple[tuple[Block, frozenset[Register]], ...] = ()

    def error(self) -> DeviceException | FrameError | None:
        """What the read failed at, as ``rtupoll read`` exits with it after printing every
        value: fields refused (exit 5), then a factor that reads no ratio (exit 7)."""
        if self.refused:
            from rtupoll.jobs.holes import FieldsRefused

            return FieldsRefused(self.refused)
        if self.unscaled:
            u = self.unscaled[0]
            return FrameError(f"unit {self.unit}: {u.field.name} not scaled: {u.reason}")
        return None


async def read_fields(bus: BusLike, profile: Profile, unit: int, fields: Sequence[Field], *,
                      timeout: float | None = None, retries: int | None = None,
                      variant: int | None = None, probe: bool = False,
                      holes: Collection[Register] = ()) -> Read:
    """Read ``fields`` in the fewest requests the profile allows (``rtupoll read``, MQTT
    ``get``).

    ``variant`` (from ``probe_variant``) drops fields the device does not have; None reads
    every field asked for, unless ``probe``: then the variant is asked first when the
    fields need it (``needs_variant``). ``holes``: registers the device is known to refuse,
    never bridged. A block refused with exception 02 is bisected (``read_planned``), so
    every field that answers is read and each refused one named. A timeout or a garbled
    reply propagates; what the device refuses, or a factor (``scale_by``) that reads no
    ratio, is in the ``Read`` (``Read.error``).
    """
    t = timing(profile, timeout, retries)
    missing: dict[str, str] = {}
    if probe and needs_variant(profile, fields):
        variant = (await probe_variant(bus, profile, unit, timeout=t.timeout,
                                       retries=t.retries)).number
    if variant is not None and profile.variant is not None:
        for f in fields:
            if f.since > variant:
                missing[f.name] = f"not present ({profile.variant.name} {variant})"
    got: list[FieldValue] = []
    refused: list[tuple[Field, DeviceException]] = []
    learned: list[tuple[Block, frozenset[Register]]] = []
    for block in plan(fields, profile, variant=variant, holes=holes):
        part = await read_planned(bus, unit, block, timeout=t.timeout, retries=t.retries)
        got += part.values
        refused += part.refused
        if part.holes:
            learned.append((block, part.holes))
    for f, exc in refused:
        missing[f.name] = f"refused: exception {exc.code:02d} {exception_name(exc.code)}"
    values, unscaled = scale_values(got, missing)  # scale_by: x the factors read
    for u in unscaled:
        missing[u.field.name] = f"not scaled: {u.reason}"
    by_name = {fv.field.name: fv for fv in values}
    out = [by_name.pop(f.name) for f in fields if f.name in by_name]
    return Read(unit, tuple(out), missing, tuple(refused), tuple(unscaled), variant,
                tuple(learned))


@mutable(slots=True)
class Variant:
    """What probing the variant gave: the device's variant (None: the profile has none)
    and the probe's evidence (``rtu.transaction.Evidence``, also of an exception reply
    that is an answer; None: nothing was asked)."""

    number: int | None
    evidence: Evidence | None = None


async def probe_variant(bus: BusLike, profile: Profile, unit: int, *,
                        timeout: float | None = None, retries: int | None = None,
                        patience: float = 0.0, idle_gap: float | None = None) -> Variant:
    """The device's variant (e.g. IRNET data structure) and the probe's evidence.

    Reads ``variant.field`` by itself (``patience``, ``idle_gap``: ``BusLike.read``'s);
    an exception reply whose code is listed in ``variant.on_exception`` is an answer too
    (IRNET: exception 02 = structure 0). Any other error propagates, with its evidence.
    """
    if profile.variant is None:
        return Variant(None)
    field = profile.field(profile.variant.field)
    t = timing(profile, timeout, retries)
    try:
        (block,) = plan([field], profile)
        got = await read_block(bus, unit, block, timeout=t.timeout, retries=t.retries,
                               patience=patience, idle_gap=idle_gap)
    except DeviceException as exc:
        if exc.code in profile.variant.on_exception:
            return Variant(profile.variant.on_exception[exc.code], exc.evidence)
        raise
    (fv,) = got.values
    value = fv.code if fv.code is not None else fv.value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        error = FrameError(f"unit {unit}: {field.name} = {fv.text!r} is not a variant number")
        error.evidence = got.evidence
        raise error
    return Variant(int(value), got.evidence)
