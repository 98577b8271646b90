"""The fields of a profile a captured frame carries (``rtupoll decode --profile``), pure.

``rtupoll.rtu.capture`` splits and decodes the frames (registers, bits, notes); this
module puts a profile on them: which fields lie in a frame's address range and, where
the frame carries their registers, their values.
"""

from __future__ import annotations

from rtupoll.frozen import frozen
from rtupoll.model.codec import Value
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Profile
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


def carried(frame: Frame, profile: Profile) -> list[Carried]:
    """The fields of ``profile`` inside the frame's address range, decoded where it has data.

    A field only partly inside is listed as partial (reading half a float is a classic
    cause of nonsense values), with no value.
    """
    if frame.table is None or frame.start is None or frame.kind not in ("request", "response"):
        return []
    count = frame.count if frame.count is not None else len(frame.values)
    lo, hi = frame.start, frame.start + count
    has_data = bool(frame.values) and (frame.kind == "response" or frame.function in (5, 6, 15, 16))
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
        fv = interpret(f, raw)
        # a sentinel ("not available") is its name, never the number its registers spell
        text = fv.text + (f" {f.unit}" if f.unit and fv.present else "")
        out.append(Carried(f.name, written, f.unit, raw, fv.output, text, fv.severity.value))
    return out
