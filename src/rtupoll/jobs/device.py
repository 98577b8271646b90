"""A profile at an address on a bus: read fields through the planner, probe the variant.

The glue between the pure layers (profile, planner, reading) and the bus. Timeouts
and retries default to the profile's ``limits``, because the device's manual, not
the caller, knows how slow it is and whether it drops the first request after
power-up. Fields the device's variant does not have (``since`` above it) are left
out of the plan rather than read into an exception reply.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from rtupoll.errors import DeviceException, FrameError
from rtupoll.io.interface import BusLike
from rtupoll.model.interpret import FieldValue
from rtupoll.model.planner import Block, decode_block, plan
from rtupoll.model.profile import Field, Limits, Profile
from rtupoll.model.scaling import scale_values

__all__ = ["Timing", "probe_variant", "read_block", "read_fields", "timing"]


@dataclass(frozen=True)
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


async def read_block(bus: BusLike, unit: int, block: Block, *, timeout: float,
                     retries: int) -> list[FieldValue]:
    """One planned read, decoded. Bus errors propagate (the scheduler resumes here)."""
    words = await bus.read(unit, block.table, block.address, block.count,
                           timeout=timeout, retries=retries)
    return decode_block(block, words)


async def read_fields(bus: BusLike, profile: Profile, unit: int, fields: Sequence[Field], *,
                      timeout: float | None = None, retries: int | None = None,
                      variant: int | None = None) -> list[FieldValue]:
    """Read ``fields`` in the fewest requests the profile allows; values in request order.

    ``variant`` (from ``probe_variant``) drops fields the device does not have; None
    reads every field asked for. The first failing block raises its bus error; a field
    whose ``scale_by`` factor reads no ratio (0, a sentinel) raises ``FrameError``.
    """
    t = timing(profile, timeout, retries)
    got: list[FieldValue] = []
    for block in plan(fields, profile, variant=variant):
        got += await read_block(bus, unit, block, timeout=t.timeout, retries=t.retries)
    values, unscaled = scale_values(got)
    if unscaled:  # a factor (scale_by) read, but it is no ratio: no value, an error
        raise FrameError(f"unit {unit}: {unscaled[0].field.name} not scaled: "
                         f"{unscaled[0].reason}")
    by_name = {fv.field.name: fv for fv in values}
    out: list[FieldValue] = []
    for f in fields:
        if f.name in by_name:  # a field asked for twice comes back once
            out.append(by_name.pop(f.name))
    return out


async def probe_variant(bus: BusLike, profile: Profile, unit: int, *,
                        timeout: float | None = None, retries: int | None = None
                        ) -> int | None:
    """The device's variant (e.g. IRNET data structure), or None if the profile has none.

    Reads ``variant.field`` by itself; an exception reply whose code is listed in
    ``variant.on_exception`` is an answer too (IRNET: exception 02 = structure 0).
    Any other error propagates.
    """
    if profile.variant is None:
        return None
    field = profile.field(profile.variant.field)
    try:
        (fv,) = await read_fields(bus, profile, unit, [field], timeout=timeout, retries=retries)
    except DeviceException as exc:
        if exc.code in profile.variant.on_exception:
            return profile.variant.on_exception[exc.code]
        raise
    value = fv.code if fv.code is not None else fv.value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise FrameError(f"unit {unit}: {field.name} = {fv.text!r} is not a variant number")
    return int(value)
