"""Commands from the broker, through the same safe paths as ``rtupoll write`` and ``read``.

``BASE/DEVICE/set`` with ``{"FIELD": value, ...}``: every field is checked first
(writes switched on, not an address or baud-rate field unless the site file allows
it, then ``jobs.writes.plan_write``: read-only, range, ``values:``, enum names), and
nothing is sent unless all pass; then each is written with the device's function
code, read back and compared (``jobs.writes.verify``). The answer on
``BASE/DEVICE/set/result`` carries the CLI's wording and exit code:

    {"status": "ok", "exit_code": 0, "values": {"measurement_1_mode": "TBB"}}
    {"status": "refused", "exit_code": 8, "error": "measurement_1 is read-only (...)"}

``BASE/DEVICE/get``: empty (or ``{}``) reads the whole device now, ahead of the
schedule; a list of field names (or ``{"fields": [...]}``) reads those fields, polled
or not, as ``rtupoll read`` reads them (the one read job, with the variant and the holes
the poller learned), and answers on ``BASE/DEVICE/get/result`` like ``set``: a field the
device refuses is an exception (exit code 5) whose ``values`` hold what was read.

Whatever a payload holds, it is bounded before it is parsed (``MAX_PAYLOAD`` bytes,
``MAX_DEPTH`` levels of nesting), a key given twice is refused (JSON would silently keep
the last), and a number is a JSON number or a plain decimal string (``"12.5"``): not
``true``, ``"1_0"``, ``"0x10"``, ``"1e1"`` or full-width digits. A number the field cannot
hold (``1e39`` for an f32) is refused like any value out of range.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Collection, Sequence
from typing import TYPE_CHECKING, Any

from rtupoll.errors import (
    RefusedError,
    RtupollError,
    UsageError,
)
from rtupoll.jobs.device import Timing
from rtupoll.jobs.writes import WriteOp, plan_write, read_back, verify, write
from rtupoll.model.codec import DataType, value_range
from rtupoll.model.interpret import FieldValue
from rtupoll.model.profile import Field, Poll, Profile
from rtupoll.model.record import finite

if TYPE_CHECKING:
    from rtupoll.config.site import DeviceConfig
    from rtupoll.io.interface import BusLike
    from rtupoll.jobs.scheduler import DevicePoller

WRITES_OFF = ("writes over MQTT are off: start poll with --mqtt-allow-writes, or set "
              "mqtt.allow_writes: true in the site file")


MAX_PAYLOAD = 16_384  # bytes of a command's payload
MAX_DEPTH = 4  # nesting of a command's JSON ({"fields": [...]} is 2)
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)", re.ASCII)  # no exponent
_PROTECTED = {"address": "the device's own address", "baud": "the device's baud rate"}


def protected(profile: Profile, field: Field) -> str:
    """Why writing ``field`` could cut the device off the bus ('' when it cannot)."""
    return _PROTECTED.get(profile.line_setting(field), "")


def _object(payload: bytes, what: str) -> Any:
    """The command's JSON, bounded in size and depth before it is parsed."""
    if len(payload) > MAX_PAYLOAD:
        raise UsageError(f"{what}: the payload is {len(payload)} bytes; at most "
                         f"{MAX_PAYLOAD} are taken")
    if not payload.strip():
        return None
    if depth(payload) > MAX_DEPTH:
        raise UsageError(f"{what}: the payload nests deeper than {MAX_DEPTH} levels")
    try:
        return json.loads(payload.decode("utf-8"), object_pairs_hook=_once)
    except _Twice as exc:
        raise UsageError(f"{what}: the payload has the key {exc.key} twice (each key once: "
                         "which value was meant cannot be known)") from None
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise UsageError(f"{what}: the payload is not JSON") from None


class _Twice(Exception):
    def __init__(self, key: str) -> None:
        self.key = json.dumps(key)[:40]


def _once(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose keys are all different (``json.loads`` keeps the last)."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _Twice(key)
        out[key] = value
    return out


def depth(payload: bytes) -> int:
    """How deep ``[`` and ``{`` nest in a JSON text (outside strings), without parsing it."""
    deepest = level = 0
    in_string = escaped = False
    for byte in payload:
        if in_string:
            if escaped:
                escaped = False
            elif byte == 0x5C:  # backslash
                escaped = True
            elif byte == 0x22:  # quote
                in_string = False
        elif byte == 0x22:
            in_string = True
        elif byte in (0x5B, 0x7B):
            level += 1
            deepest = max(deepest, level)
        elif byte in (0x5D, 0x7D):
            level -= 1
    return deepest


def plan_set(dev: DeviceConfig, payload: bytes, *, writes_on: bool,
             allow: Collection[str] = ()) -> list[WriteOp]:
    """Check every ``FIELD: value`` of a set command; raises before anything is sent."""
    if not writes_on:
        raise RefusedError(WRITES_OFF)
    obj = _object(payload, "set")
    if not isinstance(obj, dict) or not obj:
        raise UsageError('set: expected a JSON object {"FIELD": value, ...}')
    p = dev.profile
    ops = []
    for name, value in obj.items():
        field = p.field(str(name))
        why = protected(p, field)
        if why and field.name not in allow:
            raise RefusedError(f"{field.name} is {why}: MQTT writes it only when the site file "
                               f"allows it (mqtt.devices.{dev.name}.allow: [{field.name}])")
        text = _text(field, value)
        try:
            ops.append(plan_write(field, text, p.limits.functions))
        except (OverflowError, ValueError) as exc:  # what no check above foresaw
            raise RefusedError(f"{field.name}: {text} cannot be written: {exc}") from None
    return ops


def _text(field: Field, value: Any) -> str:
    """A JSON value as the text ``rtupoll write FIELD=TEXT`` would take: a number is a
    JSON number or a plain decimal string, and one the field can hold."""
    shown = json.dumps(value)[:60]
    named = bool(field.enum or field.flags) or field.layout.type is DataType.STRING
    if isinstance(value, bool):
        if field.layout.type is DataType.BOOL:
            return "1" if value else "0"
        raise UsageError(f"{field.name}: {shown} is not a value for it (a number is a JSON "
                         "number or a decimal string)")
    if isinstance(value, str) and (named or field.layout.type is DataType.BOOL):
        return value
    if isinstance(value, str):
        if not _DECIMAL.fullmatch(value):
            raise UsageError(f"{field.name}: {shown} is not a number (a JSON number, or a "
                             "plain decimal string such as \"12.5\")")
        number = float(value)
        _holds(field, number, value)
        return value
    if isinstance(value, int):
        _holds(field, float(value) if abs(value) < 1e300 else math.inf, str(value))
        return str(value)
    if isinstance(value, float):
        _holds(field, value, repr(value))
        return repr(value)
    if isinstance(value, list) and all(isinstance(v, str) for v in value) and field.flags:
        return "|".join(value) if value else "none"
    raise UsageError(f"{field.name}: {shown} is not a value for it")


def _holds(field: Field, number: float, text: str) -> None:
    """Refuse a number no register of the field could carry (before encoding it)."""
    if field.enum or field.flags or field.layout.type in (DataType.STRING, DataType.BOOL):
        return
    lo, hi = value_range(field.layout)
    if not math.isfinite(number) or not lo <= number <= hi:
        raise RefusedError(f"{field.name}: {text[:40]} is outside what the field can hold "
                           f"({lo:g}..{hi:g})")


async def apply_set(bus: BusLike, dev: DeviceConfig, ops: Sequence[WriteOp],
                    done: dict[str, Any]) -> None:
    """Write, read back and verify each op in turn; ``done`` collects what each field
    holds now (a failure part-way leaves the earlier ones in it)."""
    timing = Timing(dev.response_timeout, dev.retry_count)
    for op in ops:
        sent, _ = await write(bus, dev.address, op, timing)  # an echo is checked by the bus
        if "R" not in op.field.access or dev.profile.line_setting(op.field) == "address":
            done[op.field.name] = None  # write-only, or the device has moved: not read back
            continue
        now = await read_back(bus, dev.address, op.field, timing)
        verify(op, sent, now)
        done[op.field.name] = value_of(now)


def plan_get(dev: DeviceConfig, payload: bytes) -> list[Field] | None:
    """The fields a get command names (None: the whole device, as polled)."""
    obj = _object(payload, "get")
    if isinstance(obj, dict):
        obj = obj.get("fields") if obj else None
    if obj is None or obj == []:
        return None
    if not isinstance(obj, list) or not all(isinstance(n, str) for n in obj):
        raise UsageError('get: expected nothing, a list of field names or {"fields": [...]}')
    fields = []
    for name in dict.fromkeys(obj):
        f = dev.profile.field(name)
        if f.poll is Poll.NEVER:
            raise RefusedError(f"{name} is never polled: reading it has side effects "
                               f"({f.description or 'see the profile'}); use 'rtupoll read'")
        fields.append(f)
    return fields


async def apply_get(bus: BusLike, dev: DevicePoller, fields: Sequence[Field],
                    done: dict[str, Any]) -> dict[str, Any]:
    """``fields`` read now as ``rtupoll read`` reads them (``DevicePoller.read_now``: the
    one read job, with the variant and the holes the poller learned); ``done`` gets each
    field's value as ``read --format json`` gives it (null: not in the device's variant,
    or refused), which a failure (a field refused, exit 5) carries too."""
    got = await dev.read_now(bus, fields)
    read = {fv.field.name: value_of(fv) for fv in got.values}
    done.update((f.name, read.get(f.name)) for f in fields)
    error = got.error()
    if error is not None:
        raise error
    return dict(done)


def value_of(fv: FieldValue) -> Any:
    """A field's value as every JSON output gives it (``model.record.record``'s ``value``:
    null for a sentinel, NaN or infinity)."""
    return finite(fv.output)


def ok(values: dict[str, Any]) -> dict[str, Any]:
    return {"status": "ok", "exit_code": 0, "values": values}


def failed(exc: RtupollError, values: dict[str, Any] | None = None) -> dict[str, Any]:
    """The CLI's one line and exit code, as a result payload."""
    out: dict[str, Any] = {"status": exc.status, "exit_code": exc.exit_code,
                           "error": str(exc)}
    if values:
        out["values"] = values  # written (and read back) before the failure; a get's read
    return out
