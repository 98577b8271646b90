"""click parameter types for the domain: device specs, addresses, register specs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import click


def parse_int(text: str) -> int:
    """Decimal, 0x hex or a trailing h (``0xFE``, ``254``, ``FEh``)."""
    t = text.strip().lower()
    if t.endswith("h") and len(t) > 1:
        return int(t[:-1], 16)
    return int(t, 0)


@dataclass(frozen=True)
class DeviceSpec:
    """``PROFILE@ADDRESS``: a profile id (or YAML path) and a unit address."""

    profile: str
    address: int

    def __str__(self) -> str:
        return f"{self.profile}@{self.address}"


class DeviceSpecType(click.ParamType[DeviceSpec, Any]):
    name = "PROFILE@ADDRESS"

    def convert(self, value: object, param: click.Parameter | None,
                ctx: click.Context | None) -> DeviceSpec:
        if isinstance(value, DeviceSpec):
            return value
        text = str(value)
        profile, sep, addr = text.rpartition("@")
        if not sep or not profile:
            self.fail(f"{text!r} is not PROFILE@ADDRESS (e.g. net-irnet-pro@1)", param, ctx)
        try:
            address = parse_int(addr)
        except ValueError:
            self.fail(f"{addr!r} in {text!r} is not an address (0-255, decimal or 0x..)",
                      param, ctx)
        if not 0 <= address <= 255:
            self.fail(f"address {address} in {text!r} is outside 0..255", param, ctx)
        return DeviceSpec(profile, address)


class UnitType(click.ParamType[int, Any]):
    """A unit (slave) address, 0..255, decimal or hex."""

    name = "ADDRESS"

    def convert(self, value: object, param: click.Parameter | None,
                ctx: click.Context | None) -> int:
        if isinstance(value, int):
            return value
        try:
            address = parse_int(str(value))
        except ValueError:
            self.fail(f"{value!r} is not an address (0-255, decimal or 0x..)", param, ctx)
        if not 0 <= address <= 255:
            self.fail(f"address {address} is outside 0..255", param, ctx)
        return address


DEVICE = DeviceSpecType()
UNIT = UnitType()
