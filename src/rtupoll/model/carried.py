"""The fields of a profile a captured frame carries (``rtupoll decode --profile``), pure.

``rtupoll.rtu.capture`` splits and decodes the frames (registers, bits, notes); this
module puts a profile on them: which fields lie in a frame's address range and, where
the frame carries their registers, their values. A field with ``scale_by`` is scaled
by its factors from the same frame or, in a capture (``carried_in``), the latest earlier
frame of the same unit that carried them; otherwise it has no value, and the text says
what the terminals read and why it is not the reading.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from rtupoll.frozen import frozen
from rtupoll.model.codec import Value
from rtupoll.model.interpret import FieldValue, display, interpret
from rtupoll.model.profile import Profile
from rtupoll.model.scaling import Unscaled, scale
from rtupoll.rtu.capture import Frame


@frozen
class Carried:
    """A profile field that a frame carries (a reply, a write) or asks for (a read request)."""

    name: str
    written: str  # the address as the profile's manual writes it
    unit: str = ""
    raw: tuple[int, ...] = ()
    value: Value | None = None  # None: a request, or only part of the field is in the frame
    text: str = ""
    severity: str = ""
    partial: bool = False


def carried_in(frames: Sequence[Frame], profile: Profile) -> list[list[Carried]]:
    """``carried`` for each frame of a capture, in order: a scaled field takes the latest
    values of its factors the capture has shown for the same unit (a ratio read before)."""
    seen: dict[int | None, dict[str, FieldValue]] = {}
    out = []
    for frame in frames:
        mine = seen.setdefault(frame.unit, {})
        whole = _whole(frame, profile)
        out.append(_carried(frame, profile, {**mine, **whole}))
        mine.update(whole)
    return out


def carried(frame: Frame, profile: Profile, seen: Mapping[str, FieldValue] | None = None
            ) -> list[Carried]:
    """The fields of ``profile`` inside the frame's address range, decoded where it has data.

    A field only partly inside is listed as partial (reading half a float is a classic
    cause of nonsense values), with no value. ``seen``: fields decoded from earlier frames
    of the same unit, for the factors of a ``scale_by`` field this frame does not carry.
    """
    return _carried(frame, profile, {**(seen or {}), **_whole(frame, profile)})


def _carried(frame: Frame, profile: Profile, got: Mapping[str, FieldValue]) -> list[Carried]:
    """``carried``, given the fields decoded so far (this frame's whole ones among them)."""
    if frame.table is None or frame.start is None or frame.kind not in ("request", "response"):
        return []
    count = frame.count if frame.count is not None else len(frame.values)
    lo, hi = frame.start, frame.start + count
    has_data = _has_data(frame)
    out: list[Carried] = []
    for f in profile.fields:
        if f.table is not frame.table or f.end <= lo or f.address >= hi:
            continue
        written = profile.written(f)
        if f.address < lo or f.end > hi:
            out.append(Carried(f.name, written, f.unit, partial=True))
            continue
        if not has_data or f.end - lo > len(frame.values):
            out.append(Carried(f.name, written, f.unit))
            continue
        raw = frame.values[f.address - lo : f.end - lo]
        fv = scale(got[f.name], got)
        if isinstance(fv, Unscaled):  # its ratio is not in the capture: no value, and why
            terminals = got[f.name].text + (f" {f.unit}" if f.unit else "")
            out.append(Carried(f.name, written, f.unit, raw, None,
                               f"{terminals} at the terminals, not scaled: {fv.reason}",
                               "warning"))
            continue
        # a sentinel ("not available") is its name, never the number its registers spell
        shown, unit = display(fv)  # kelvin as °C, as every screen shows it
        text = shown + (f" {unit}" if unit and fv.present else "")
        out.append(Carried(f.name, written, f.unit, raw, fv.output, text, fv.severity.value))
    return out


def _has_data(frame: Frame) -> bool:
    return bool(frame.values) and (frame.kind == "response" or frame.function in (5, 6, 15, 16))


def _whole(frame: Frame, profile: Profile) -> dict[str, FieldValue]:
    """Every field the frame carries whole, decoded as stored."""
    if frame.table is None or frame.start is None or not _has_data(frame):
        return {}
    lo = frame.start
    end = lo + min(len(frame.values), frame.count if frame.count is not None
                   else len(frame.values))
    return {f.name: interpret(f, frame.values[f.address - lo : f.end - lo])
            for f in profile.fields if f.table is frame.table and lo <= f.address
            and f.end <= end}
