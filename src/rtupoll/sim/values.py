"""Plausible values for simulated fields: where they start and how they move.

A simulated device should look alive to a person watching ``rtupoll poll``: measurements
wander inside their documented range, now and then an error code or a warning flag shows
up for a few seconds, and configuration (firmware, serial numbers, addresses) stays put.
Nothing here names a device: every choice follows from the profile's field description
(type, range, enum and flag severities, ``poll`` class), and every random draw comes from
one seeded generator, so a seed replays the same story.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

from rtupoll.model.codec import DataType, Value, bits_range
from rtupoll.model.profile import Field, Poll, Profile, Severity

# chance per tick that an enum leaves its normal code or a flag shows up: with a dozen
# coded fields on a bus, an episode every twenty seconds or so, not a wall of alarms
EVENT_RATE = 0.005
EVENT_TICKS = (2, 6)  # how many ticks such an event lasts


def value_range(field: Field, profile: Profile) -> tuple[float, float]:
    """The span a field's value lives in: its ``range``, an identify check's, or a default."""
    if field.minimum is not None and field.maximum is not None:
        return field.minimum, field.maximum
    for check in profile.identify:
        if check.field == field.name and check.range is not None:
            return check.range
    t = field.layout.type
    if isinstance(field.typical, (int, float)):
        # around the everyday value the profile gives, never across zero from it
        half = abs(field.typical) * 0.5 or 1.0
        lo_t, hi_t = field.typical - half, field.typical + half
        if t.is_integer:
            blo, bhi = sorted(v * field.layout.scale + field.layout.offset
                              for v in bits_range(field.layout))
            lo_t, hi_t = max(lo_t, blo), min(hi_t, bhi)
        return lo_t, hi_t
    if t.is_float:
        return 0.0, 100.0
    lo, hi = bits_range(field.layout) if t.is_integer else (0, 1)
    scale, offset = field.layout.scale, field.layout.offset
    lo_v, hi_v = sorted((lo * scale + offset, hi * scale + offset))
    # a default span that is clearly a value, not a full-scale or wrapped-around number
    return max(lo_v, 0.0 if lo >= 0 else -100.0 * abs(scale)), min(hi_v, 1000.0 * abs(scale))


def quantize(field: Field, value: float) -> int | float:
    """Round to what the field can carry (integer types hold ``raw * scale + offset``)."""
    t = field.layout.type
    if not t.is_integer:
        return value
    scale, offset = field.layout.scale, field.layout.offset
    raw = round((value - offset) / scale)
    lo, hi = bits_range(field.layout)
    raw = min(max(raw, lo), hi)
    if scale == 1 and offset == 0:
        return int(raw)
    return round(raw * scale + offset, 9)


# units whose everyday value is known: a room, not the middle of the sensor's range
_TYPICAL = {"°C": (18.0, 26.0), "degC": (18.0, 26.0), "C": (18.0, 26.0), "K": (291.0, 299.0),
            "%RH": (30.0, 60.0), "%": (30.0, 60.0)}


def _typical(field: Field, lo: float, hi: float, rng: random.Random) -> float:
    """Where a measurement starts: the profile's ``typical`` value, else typical for its
    unit, else low in a range that starts at zero (concentrations, distances), else
    mid-range."""
    if isinstance(field.typical, (int, float)):
        return float(field.typical)
    if field.unit in _TYPICAL:
        return rng.uniform(*_TYPICAL[field.unit])
    share = rng.uniform(0.05, 0.3) if lo >= 0 else rng.uniform(0.3, 0.6)
    return lo + (hi - lo) * share


class Motion:
    """How one field's value evolves tick by tick. ``value`` is what the image shows."""

    value: Value

    def step(self, rng: random.Random) -> None:
        """Advance one tick (a no-op for values that never change)."""

    def on_read(self) -> bool:
        """Called when a request reads the field; True if that changed the value."""
        return False


@dataclass
class Static(Motion):
    value: Value


STEP = 0.003  # a walk's step per tick, as a share of its span
PULL = 0.02  # how strongly it returns home per tick: it wanders about 1.5 % of its span


class Walk(Motion):
    """A mean-reverting random walk inside ``[lo, hi]``: looks like a real measurement,
    moving slowly as physical quantities do (a room's temperature drifts by tenths of a
    degree, not by ten degrees a minute)."""

    def __init__(self, field: Field, lo: float, hi: float, rng: random.Random) -> None:
        self.field, self.lo, self.hi = field, lo, hi
        self.home = min(max(_typical(field, lo, hi, rng), lo), hi)
        self.x = self.home
        self.value = quantize(field, self.x)

    @property
    def span(self) -> float:
        """How far the value may plausibly wander: the everyday band, not the sensor's
        whole range (an NDIR sensor's 200-400 K is not a room's temperature)."""
        span = self.hi - self.lo
        if isinstance(self.field.typical, (int, float)):  # stay near it: values agree
            return min(span, abs(self.field.typical) * 0.2)
        if self.field.unit in _TYPICAL:
            lo, hi = _TYPICAL[self.field.unit]
            return min(span, hi - lo)
        return span

    def step(self, rng: random.Random) -> None:
        self.x += rng.gauss(0.0, self.span * STEP) + (self.home - self.x) * PULL
        self.x = min(max(self.x, self.lo), self.hi)
        self.value = quantize(self.field, self.x)


class Counter(Motion):
    """A total that only grows (``counter: true``): energy, operating hours."""

    def __init__(self, field: Field, start: float, rate: float) -> None:
        self.field, self.x, self.rate = field, start, rate
        self.value = quantize(field, self.x)

    def step(self, rng: random.Random) -> None:
        self.x += rng.uniform(0.5, 1.5) * self.rate
        value = quantize(self.field, self.x)
        if isinstance(value, (int, float)) and isinstance(self.value, (int, float)):
            self.value = max(value, self.value)  # clamped at the top: stays, never wraps


class Events(Motion):
    """An enum or flags field: its normal code, with short-lived abnormal episodes."""

    def __init__(self, normal: int, abnormal: list[int]) -> None:
        self.normal, self.abnormal = normal, abnormal
        self.value = normal
        self.left = 0

    def step(self, rng: random.Random) -> None:
        if self.left > 0:
            self.left -= 1
            if self.left == 0:
                self.value = self.normal
        elif self.abnormal and rng.random() < EVENT_RATE:
            self.value = rng.choice(self.abnormal)
            self.left = rng.randint(*EVENT_TICKS)


class Peak(Motion):
    """A peak-hold register whose read resets it (``poll: never``): rises, drops on read."""

    def __init__(self, field: Field, lo: float, hi: float) -> None:
        self.field, self.lo, self.hi = field, lo, hi
        self.value = quantize(field, lo + (hi - lo) * 0.5)

    def step(self, rng: random.Random) -> None:
        assert isinstance(self.value, (int, float))
        sample = self.lo + (self.hi - self.lo) * rng.uniform(0.2, 0.8)
        self.value = max(self.value, quantize(self.field, sample))

    def on_read(self) -> bool:
        before = self.value
        self.value = quantize(self.field, self.lo)
        return before != self.value


def _abnormal_codes(field: Field) -> tuple[int, list[int]]:
    """The code an enum shows as a rule (the profile's ``typical``, else its first ok
    code) and the codes of its abnormal episodes."""
    normal = min((c for c, ch in field.enum.items() if ch.severity is Severity.OK), default=0)
    if isinstance(field.typical, (int, float)) and field.typical in field.enum:
        normal = int(field.typical)
    others = [c for c, ch in field.enum.items() if ch.severity is not Severity.OK]
    if not others and field.other is not None and field.other.severity is not Severity.OK:
        top = max(field.enum, default=0)
        others = list(range(top + 1, top + 6))  # undocumented codes the profile calls "other"
    return normal, others


def motion_for(field: Field, profile: Profile, rng: random.Random) -> Motion:
    """The behaviour a field gets when nothing pins it."""
    t = field.layout.type
    if t is DataType.STRING:
        if isinstance(field.typical, str):
            return Static(field.typical)
        return Static(f"SIM-{field.name}".upper()[: 2 * field.words])
    if t is DataType.BOOL:
        return Static(False)
    if field.enum:
        normal, others = _abnormal_codes(field)
        return Events(normal, others) if field.poll is Poll.DEFAULT else Static(normal)
    if field.flags:
        bits = [m for m, ch in field.flags.items() if ch.severity is not Severity.OK] \
            or list(field.flags)
        return Events(0, bits) if field.poll is Poll.DEFAULT else Static(0)
    lo, hi = value_range(field, profile)
    if field.counter:
        start = float(field.typical) if isinstance(field.typical, (int, float)) \
            else lo + (hi - lo) * rng.uniform(0.01, 0.1)
        step = abs(field.layout.scale) if t.is_integer else max(abs(start), 1.0) * 1e-5
        return Counter(field, start, step)
    if field.poll is Poll.NEVER:
        return Peak(field, lo, hi)
    if field.poll is Poll.DEFAULT:
        return Walk(field, lo, hi, rng)
    if field.typical is not None:
        return Static(quantize(field, float(field.typical)))
    return Static(quantize(field, rng.uniform(lo, lo + (hi - lo) / 4)))
