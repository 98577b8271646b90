"""Simulated values that agree with each other, as a real device's do.

``values.motion_for`` gives each field a plausible life of its own; on a real device
some fields are one quantity seen twice, and a technician who sees them disagree calls
the device (or the tool) broken. ``make_consistent`` ties them together after a device
is built:

- the same quantity in two units (``air_gap_cm`` and ``air_gap_mm``: the same
  description, units a fixed factor apart) -- the second follows the first;
- a level derived from its reading (the Huiwen's ``pm25_level`` from ``pm25``), by
  bands: the manual names the levels but gives no thresholds, so the simulator uses
  ``LEVEL_BANDS`` (China's HJ 633 PM2.5 breakpoints, common indoor-air guidance for the
  gases) -- plausible, not the vendor's. Unless the profile gives a ``typical`` value,
  such a reading wanders in the first two bands: an ordinary room, not an alarm;
- a value inside what the device can report: a field with a ``values:`` list takes
  one of them (no 23300 baud);
- configuration that describes the line (a baud-rate register or code) says the
  line's speed;
- a distance and what it leaves of a fixed height (a radar's air gap and the water
  level under it): the air gap is the mounting height minus the level, so the two
  always add up, and the level moves slowly;
- an energy counter integrates the device's power (an import counter grows with the
  power drawn, an export counter with the power fed back, a total with both), at the
  rate that power gives: 3.1 kW adds 0.86 Wh a second.

A field pinned by ``--set`` or a scenario is left as pinned.
"""

from __future__ import annotations

import random
import re
from collections.abc import Mapping, MutableMapping, Sequence

from rtupoll.model.codec import Value
from rtupoll.model.profile import Field, Profile
from rtupoll.sim.values import Motion, Static, Walk, quantize

# unit -> (dimension, size in the dimension's smallest unit)
UNITS: Mapping[str, tuple[str, float]] = {
    "mm": ("length", 1.0), "cm": ("length", 10.0), "m": ("length", 1000.0),
    "Pa": ("pressure", 1.0), "hPa": ("pressure", 100.0), "kPa": ("pressure", 1000.0),
    "mbar": ("pressure", 100.0), "bar": ("pressure", 100_000.0),
    "Wh": ("energy", 1.0), "kWh": ("energy", 1000.0), "MWh": ("energy", 1e6),
    "W": ("power", 1.0), "kW": ("power", 1000.0),
    "mA": ("current", 1.0), "A": ("current", 1000.0),
    "mV": ("voltage", 1.0), "V": ("voltage", 1000.0),
}

# level field -> (reading field, upper bound of each level but the last); by profile id
LEVEL_BANDS: Mapping[str, Mapping[str, tuple[str, tuple[float, ...]]]] = {
    "huiwen-aq": {
        "pm25_level": ("pm25", (35, 75, 115, 150, 250)),  # µg/m³, HJ 633-2012
        "tvoc_level": ("tvoc", (0.3, 0.6, 1.0, 3.0, 10.0)),  # ppm
        "hcho_level": ("hcho", (0.08, 0.1, 0.3, 0.5, 1.0)),  # ppm
        "co2_level": ("co2", (1000, 1500, 2000, 3000, 5000)),  # ppm
    },
}


def _number(m: Motion) -> float | None:
    """A motion's value as a number, at full resolution for a walk."""
    if isinstance(m, Walk):
        return m.x
    return float(m.value) if isinstance(m.value, (int, float)) and \
        not isinstance(m.value, bool) else None


class Converted(Motion):
    """The same quantity as another field, in another unit."""

    def __init__(self, field: Field, motions: Mapping[str, Motion], source: str,
                 factor: float) -> None:
        self.field, self.motions, self.source, self.factor = field, motions, source, factor
        self._shown: Value = self.value

    @property
    def value(self) -> Value:  # type: ignore[override]
        x = _number(self.motions[self.source])
        return 0 if x is None else quantize(self.field, x * self.factor)

    def step(self, rng: random.Random) -> None:
        self._shown = self.value

    def on_read(self) -> bool:  # the source may have been pinned since
        before, self._shown = self._shown, self.value
        return before != self._shown


class Banded(Motion):
    """An enum level that follows a reading: the band the reading is in."""

    def __init__(self, field: Field, motions: Mapping[str, Motion], source: str,
                 bounds: Sequence[float]) -> None:
        self.field, self.motions, self.source, self.bounds = field, motions, source, bounds
        self.codes = sorted(field.enum)
        self._shown: Value = self.value

    @property
    def value(self) -> Value:  # type: ignore[override]
        x = _number(self.motions[self.source])
        band = sum(1 for b in self.bounds if x is not None and x > b)
        return self.codes[min(band, len(self.codes) - 1)]

    def step(self, rng: random.Random) -> None:
        self._shown = self.value

    def on_read(self) -> bool:
        before, self._shown = self._shown, self.value
        return before != self._shown


class Complement(Motion):
    """What a length leaves of a fixed total: ``total - source`` (in this field's unit)."""

    def __init__(self, field: Field, motions: Mapping[str, Motion], source: str,
                 total: float, factor: float) -> None:
        self.field, self.motions, self.source = field, motions, source
        self.total, self.factor = total, factor  # factor: source unit -> this field's unit
        self._shown: Value = self.value

    @property
    def value(self) -> Value:  # type: ignore[override]
        x = _number(self.motions[self.source])
        return 0 if x is None else quantize(self.field, max(self.total - x * self.factor, 0.0))

    def step(self, rng: random.Random) -> None:
        self._shown = self.value

    def on_read(self) -> bool:
        before, self._shown = self._shown, self.value
        return before != self._shown


class Integrating(Motion):
    """An energy counter fed by a power reading: each tick adds power x tick."""

    def __init__(self, field: Field, motions: Mapping[str, Motion], source: str,
                 start: float, per_tick: float, sign: int) -> None:
        self.field, self.motions, self.source = field, motions, source
        self.x, self.per_tick, self.sign = start, per_tick, sign
        self.value = quantize(field, start)

    def step(self, rng: random.Random) -> None:
        power = _number(self.motions[self.source]) or 0.0
        if self.sign:  # import: power drawn (> 0); export: power fed back (< 0)
            power = max(power * self.sign, 0.0)
        self.x += abs(power) * self.per_tick
        value = quantize(self.field, self.x)
        if isinstance(value, (int, float)) and isinstance(self.value, (int, float)):
            self.value = max(value, self.value)  # clamped at the top: stays, never wraps


def _power_source(fields: Sequence[Field], motions: Mapping[str, Motion]) -> Field | None:
    """The device's total power: a walking power field, ``total`` in its name first,
    else the largest."""
    powers = [f for f in fields if UNITS.get(f.unit, ("", 0.0))[0] == "power"
              and isinstance(motions.get(f.name), Walk)]
    return max(powers, key=lambda f: ("total" in f.name,
                                      abs(_number(motions[f.name]) or 0.0)), default=None)


def _physics(fields: Sequence[Field], motions: MutableMapping[str, Motion],
             pinned: Sequence[str], tick: float) -> list[str]:
    """The air gap / level complement and energy counters fed by power."""
    changed: list[str] = []
    free = [f for f in fields if f.name not in pinned]
    for f in free:  # air gap = mounting height - level
        dim = UNITS.get(f.unit, ("", 0.0))[0]
        if not f.name.startswith("air_gap") or dim != "length" \
                or not isinstance(motions.get(f.name), Walk):
            continue
        level = next((g for g in fields if g.name.startswith("level")
                      and UNITS.get(g.unit, ("", 0.0))[0] == "length"
                      and isinstance(motions.get(g.name), Walk)), None)
        if level is None:
            continue
        walk = motions[level.name]
        assert isinstance(walk, Walk)
        factor = UNITS[level.unit][1] / UNITS[f.unit][1]
        gap = _number(motions[f.name]) or 0.0
        height = gap + walk.x * factor  # the mounting height, in the air gap's unit
        motions[f.name] = Complement(f, motions, level.name, height, factor)
        changed.append(f.name)
    power = _power_source(fields, motions)
    if power is not None:
        for f in free:
            if not f.counter or UNITS.get(f.unit, ("", 0.0))[0] != "energy" \
                    or f.name in changed:
                continue
            start = _number(motions[f.name]) or 0.0
            per_tick = UNITS[power.unit][1] * tick / 3600 / UNITS[f.unit][1]
            sign = 0 if "total" in f.name else -1 if "export" in f.name else 1
            motions[f.name] = Integrating(f, motions, power.name, start, per_tick, sign)
            changed.append(f.name)
    return changed


def _rate_choice(field: Field, speed: int) -> Value | None:
    """The value a field describing the line's speed takes, if it is such a field."""
    if field.unit.lower() == "baud" or (field.values and speed in field.values):
        return speed if not field.values or speed in field.values else None
    for code, choice in field.enum.items():  # e.g. UART_9600
        if re.search(rf"(?<!\d){speed}(?!\d)", choice.name) and \
                all(re.search(r"\d{3,}", c.name) for c in field.enum.values()):
            return code
    return None


def make_consistent(profile: Profile, fields: Sequence[Field],
                    motions: MutableMapping[str, Motion], pinned: Sequence[str],
                    rng: random.Random, speed: int | None = None, tick: float = 1.0
                    ) -> list[str]:
    """Tie related fields of one device together; returns the names of fields changed.
    ``tick``: seconds per value step (what an energy counter integrates over)."""
    changed: list[str] = []
    free = [f for f in fields if f.name not in pinned]
    by_name = {f.name: f for f in fields}
    for f in free:
        if speed is not None:
            rate = _rate_choice(f, speed)
            if rate is not None:
                motions[f.name] = Static(rate)
                changed.append(f.name)
                continue
        m = motions[f.name]
        if f.values and (not isinstance(m, Static) or m.value not in f.values):
            # a setting with a list of values takes one of them and keeps it
            motions[f.name] = Static(quantize(f, rng.choice(f.values)))
            changed.append(f.name)
    for f in free:
        if f.unit not in UNITS or f.poll.value != "default" or f.name in changed:
            continue
        dim, size = UNITS[f.unit]
        twin = next((g for g in fields if g is not f and g.description == f.description
                     and g.description and UNITS.get(g.unit, ("", 0))[0] == dim
                     and isinstance(motions.get(g.name), Walk)
                     and fields.index(g) < fields.index(f)), None)
        if twin is not None:
            motions[f.name] = Converted(f, motions, twin.name, UNITS[twin.unit][1] / size)
            changed.append(f.name)
    for name, (source, bounds) in LEVEL_BANDS.get(profile.id, {}).items():
        level = by_name.get(name)
        if level is not None and source in by_name and name not in pinned:
            motions[name] = Banded(level, motions, source, bounds)
            changed.append(name)
            walk = motions[source]
            if isinstance(walk, Walk) and by_name[source].typical is None \
                    and source not in pinned:
                # a room as most are: the reading wanders in the first two bands
                walk.hi = max(min(walk.hi, bounds[1]), walk.lo)
                walk.home = walk.x = min(max(bounds[0] * 0.5, walk.lo), walk.hi)
                walk.value = quantize(walk.field, walk.x)
                changed.append(source)
    changed += _physics(fields, motions, pinned, tick)
    return changed
