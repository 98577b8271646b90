"""click parameter types for the domain: device specs, addresses, register specs."""

from __future__ import annotations

import math
from typing import Any

import click

from rtupoll.frozen import frozen
from rtupoll.numbers import parse_unit


@frozen
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
            return DeviceSpec(profile, parse_unit(addr))
        except ValueError as exc:
            self.fail(f"{exc} in {text!r}", param, ctx)


class UnitType(click.ParamType[int, Any]):
    """A unit (slave) address, 0..255, decimal or hex."""

    name = "ADDRESS"

    def convert(self, value: object, param: click.Parameter | None,
                ctx: click.Context | None) -> int:
        if isinstance(value, int):
            return value
        try:
            return parse_unit(str(value))
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


class Seconds(click.FloatRange):
    """A number of seconds within a range; NaN (which no range check catches, as it
    compares false with both bounds) and infinities are refused."""

    name = "seconds"

    def convert(self, value: Any, param: click.Parameter | None,
                ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a number of seconds", param, ctx)
        return rv


DEVICE = DeviceSpecType()
UNIT = UnitType()
