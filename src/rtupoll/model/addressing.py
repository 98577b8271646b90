"""An address change and the rules that refuse one before anything is sent, pure.

What ``set-address`` and a commissioning plan check with no bus: the profile says how
the device is readdressed (or that it cannot be), which addresses it refuses or keeps
for itself, and what other device models on the same bus keep for themselves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping

from rtupoll.errors import RefusedError
from rtupoll.frozen import frozen
from rtupoll.model.profile import Field, Profile


@frozen
class Change:
    """One address change: the device ``profile`` at ``old`` gets ``new``."""

    profile: Profile
    old: int
    new: int
    check: tuple[str, str] | None = None  # identity: (field, value as text) to match first
    where: str = ""  # plan file:line, for messages
    # addresses other device models keep for themselves on a shared bus -> why
    avoid: Mapping[int, str] = dataclasses.field(default_factory=dict)
    # other rows of its plan expect a device at ``old`` too (sensors fresh from the
    # factory): they are connected one at a time, and a row answering at ``new`` is done
    # whatever answers at ``old`` (the next sensor)
    shared: bool = False

    @property
    def label(self) -> str:
        return f"{self.profile.id}@{self.old} -> {self.new}"


def address_field(profile: Profile) -> Field:
    """The register that holds the address, or RefusedError saying what the manual says."""
    method = profile.set_address
    if method.field is None:
        raise RefusedError(f"{profile.id} cannot be readdressed from rtupoll: "
                           f"{method.unsupported}")
    return profile.field(method.field)


def shared_reserved(profiles: Iterable[Profile]) -> dict[int, str]:
    """Addresses a device model keeps for itself on any bus it is on: its reserved ones
    (CO2Meter boards: 0xCC) and its 'any device' one (0xFE). Another device given one of
    them breaks those boards the day they share its bus."""
    out: dict[int, str] = {}
    for p in profiles:
        for address, why in p.addresses.reserved.items():
            out.setdefault(address, f"reserved by {p.id} devices ({why})")
        if p.addresses.any is not None:
            out.setdefault(p.addresses.any, f"the address every {p.id} device answers")
    return out


def refuse(change: Change) -> Field:
    """Every check that needs no bus; returns the address field."""
    address = address_field(change.profile)
    why = change.profile.addresses.check(change.new)
    if why:
        raise RefusedError(f"{change.label}: {why}")
    if change.new in change.avoid:
        raise RefusedError(f"{change.label}: {change.new} (0x{change.new:02X}) is "
                           f"{change.avoid[change.new]}; --allow-reserved if no such device "
                           "is on this bus")
    if change.new == change.old:
        raise RefusedError(f"{change.label}: the device is already at {change.old}")
    if change.check:
        change.profile.field(change.check[0])  # UsageError naming the fields if unknown
    return address
