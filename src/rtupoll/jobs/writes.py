"""Writing fields and raw registers safely: refuse first, then write, then read back.

A write that goes wrong on a live plant is worse than one that never happens, so
everything that can be checked without the device is checked before the first byte
is sent (read-only fields, values outside the field's documented range, values the
type cannot hold, a function code the device does not implement), and every write
is read back: the caller learns what the register holds now, not what was sent.

Two device quirks live here rather than in each command: a device without FC06
(Banner EZ-ARRAY) gets FC16 even for one register, and a u8 field that shares its
register with another (Banner's address in the low byte of 41000) is written by
read-modify-write so the other byte survives.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from rtupoll import rtu
from rtupoll.errors import EncodeError, RefusedError, UsageError, VerificationError
from rtupoll.jobs.device import Timing
from rtupoll.model.codec import DataType, Value, check_exact, decode, words_to_hex
from rtupoll.model.interpret import FieldValue, field_words, interpret
from rtupoll.model.profile import Field
from rtupoll.model.raw import RegisterSpec, parse_values, words_of
from rtupoll.rtu import Table

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike

RAW_FUNCTIONS = frozenset({5, 6, 15, 16})  # a device with no profile: assume the usual set


@dataclass(frozen=True)
class WriteOp:
    """One write, checked and encoded: ``words`` are final unless ``shared`` (u8 RMW)."""

    field: Field
    value: Value  # what the user meant: number, enum name, flag names, text
    words: tuple[int, ...]  # for a shared-register field: with the other byte still 0
    function: int  # 5, 6 or 16

    @property
    def shared(self) -> bool:
        """The field is one byte of a register: write it by read-modify-write."""
        return self.field.layout.type in (DataType.U8, DataType.I8)

    def describe(self) -> str:
        f = self.field
        byte = f"{f.layout.byte} byte of " if self.shared else ""
        where = f"{byte}{f.table.value} {f.written or f.address} (wire 0x{f.address:04X})"
        how = rtu.FUNCTION_NAMES.get(self.function, f"function {self.function}")
        rmw = ", keeping the other byte" if self.shared else ""
        return f"{f.name} = {_show(self.value)} -> {where}, FC{self.function:02d} {how}{rmw}"


def parse_value(field: Field, text: str) -> Value:
    """The user's text as the field's kind of value: enum name or code, flags, number, text."""
    t = field.layout.type
    s = text.strip()
    if t is DataType.STRING:
        return text
    if t is DataType.BOOL:
        lowered = s.lower()
        if lowered in ("1", "on", "true", "yes"):
            return True
        if lowered in ("0", "off", "false", "no"):
            return False
        raise UsageError(f"{field.name}: {text!r} is not on/off (1/0)")
    if field.enum:
        by_name = {c.name.lower(): c.name for c in field.enum.values()}
        if s.lower() in by_name:
            return by_name[s.lower()]
        code = _number(s)
        if isinstance(code, int) and code in field.enum:
            return field.enum[code].name
        names = ", ".join(c.name for c in field.enum.values())
        raise RefusedError(f"{field.name}: {text!r} is not one of: {names}")
    if field.flags:
        if s.lower() in ("", "none", "0"):
            return []
        number = _number(s)
        if isinstance(number, int):
            return [c.name for m, c in field.flags.items() if number & m == m]
        by_name = {c.name.lower(): c.name for c in field.flags.values()}
        wanted = [p.strip().lower() for p in s.replace("|", ",").split(",") if p.strip()]
        bad = [w for w in wanted if w not in by_name]
        if bad:
            raise RefusedError(f"{field.name}: {bad[0]!r} is not one of: "
                               f"{', '.join(c.name for c in field.flags.values())}")
        return [by_name[w] for w in wanted]
    number = _number(s)
    if number is None:
        raise UsageError(f"{field.name}: {text!r} is not a number")
    return number


def choose_function(field: Field, words: int, functions: frozenset[int]) -> int:
    """FC05 for a coil, FC06 for one register when the device has it, else FC16."""
    if field.table is Table.COIL:
        if 5 in functions:
            return 5
        raise RefusedError(f"{field.name}: the device does not implement FC05 (write coil)")
    if words == 1 and 6 in functions:
        return 6
    if 16 in functions:
        return 16
    have = ", ".join(f"FC{f:02d}" for f in sorted(functions))
    raise RefusedError(f"{field.name}: the device implements no register write that fits "
                       f"({have})")


def plan_write(field: Field, text: str, functions: frozenset[int]) -> WriteOp:
    """Check and encode one ``FIELD=VALUE``; raises RefusedError before anything is sent."""
    if not field.writable:
        raise RefusedError(f"{field.name} is read-only ({field.table.value} "
                           f"{field.written or field.address}, access {field.access})")
    value = parse_value(field, text)
    check_range(field, value)
    try:
        words = field_words(field, value)
        check_exact(value, words, field.layout)
    except EncodeError as exc:
        raise RefusedError(f"{field.name}: {exc}") from None
    if field.values and value not in field.values:
        takes = ", ".join(_show(int(v) if v.is_integer() else v) for v in field.values)
        raise RefusedError(f"{field.name}: {_show(value)} is not one of the values it takes: "
                           f"{takes}")
    return WriteOp(field, value, words, choose_function(field, len(words), functions))


def check_range(field: Field, value: Value) -> None:
    """Refuse a number outside the field's documented ``range``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    lo, hi = field.minimum, field.maximum
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        unit = f" {field.unit}" if field.unit else ""
        raise RefusedError(f"{field.name}: {value:g}{unit} is outside the field's range "
                           f"{lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
                           f"{unit}")


async def write(bus: BusLike, unit: int, op: WriteOp, timing: Timing, *, reply: str = "echo"
                ) -> tuple[tuple[int, ...], bool]:
    """Send one write (read-modify-write for a shared register); return the words sent
    and whether the device confirmed them with an echo (see ``Bus.write_registers``)."""
    f = op.field
    if f.table is Table.COIL:
        await bus.write_coil(unit, f.address, bool(op.value), timeout=timing.timeout,
                             retries=timing.retries)
        return op.words, True
    words = op.words
    if op.shared:
        current = (await bus.read(unit, Table.HOLDING, f.address, 1,
                                  timeout=timing.timeout, retries=timing.retries)).values
        words = field_words(f, op.value, current)
    echoed = await bus.write_registers(unit, f.address, words, function=op.function,
                                       timeout=timing.timeout, retries=timing.retries,
                                       reply=reply)
    return words, echoed


async def read_back(bus: BusLike, unit: int, field: Field, timing: Timing) -> FieldValue:
    """Read one field (or raw run) back, as it is now."""
    words = (await bus.read(unit, field.table, field.address, field.words,
                            timeout=timing.timeout, retries=timing.retries)).values
    return interpret(field, words)


def verify(op: WriteOp, sent: Sequence[int], now: FieldValue) -> None:
    """The field must now hold what was written (compared as decoded values)."""
    f = op.field
    want = decode(tuple(sent), f.layout)
    got = decode(now.raw, f.layout)
    if want != got:
        raise VerificationError(f"{f.name}: wrote {_show(op.value)} but it reads back "
                                f"{now.text}{' ' + f.unit if f.unit else ''}")


def _number(text: str) -> int | float | None:
    s = text.strip().lower()
    try:
        if s.startswith(("0x", "-0x")):
            return int(s, 16)
        return int(s, 10)
    except ValueError:
        pass
    try:
        value = float(s)
    except ValueError:
        return None
    return value if value == value and value not in (float("inf"), float("-inf")) else None


def _show(value: Value) -> str:
    if isinstance(value, list):
        return "|".join(value) if value else "none"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


@dataclass(frozen=True)
class RawWrite:
    """A raw write of one run of registers (one transaction) or coils (one FC05 each)."""

    spec: RegisterSpec
    values: tuple[Value, ...]
    words: tuple[int, ...]
    function: int

    def describe(self) -> str:
        how = rtu.FUNCTION_NAMES.get(self.function, f"function {self.function}")
        shown = ", ".join(_show(v) for v in self.values)
        return (f"{self.spec.label(0)} = {shown} (wire 0x{self.spec.address:04X}, "
                f"{self.spec.words} {'coil' if self.spec.table is Table.COIL else 'register'}"
                f"{'s' if self.spec.words > 1 else ''}), FC{self.function:02d} {how}")


def plan_raw_write(spec: RegisterSpec, text: str, functions: frozenset[int]) -> RawWrite:
    """Check and encode ``SPEC=V[,V…]``; a spec without COUNT takes as many values as given."""
    if spec.table in (Table.INPUT, Table.DISCRETE):
        raise RefusedError(f"{spec.table.value} registers are read-only in Modbus")
    texts = parse_values(text, spec)
    if len(texts) != spec.count:
        if spec.count != 1:
            raise UsageError(f"{spec.label(0)}: {spec.count} values expected, got {len(texts)}")
        spec = dataclasses.replace(spec, count=len(texts))
    if spec.address + spec.words > 0x10000:
        raise UsageError(f"{spec.label(0)}: the values run past the last register (65535)")
    values = tuple(parse_value(f, t) for f, t in zip(spec.fields(), texts, strict=True))
    try:
        each = [field_words(f, v) for f, v in zip(spec.fields(), values, strict=True)]
        for f, v, w in zip(spec.fields(), values, each, strict=True):
            check_exact(v, w, f.layout)
        words = words_of(each)
    except EncodeError as exc:
        raise RefusedError(f"{spec.label(0)}: {exc}") from None
    return RawWrite(spec, values, words, choose_function(spec.fields()[0], len(words), functions))


async def write_raw(bus: BusLike, unit: int, rw: RawWrite, timing: Timing) -> None:
    if rw.spec.table is Table.COIL:
        for i, word in enumerate(rw.words):
            await bus.write_coil(unit, rw.spec.address + i, bool(word), timeout=timing.timeout,
                                 retries=timing.retries)
        return
    await bus.write_registers(unit, rw.spec.address, rw.words, function=rw.function,
                              timeout=timing.timeout, retries=timing.retries)


async def verify_raw(bus: BusLike, unit: int, rw: RawWrite, timing: Timing) -> list[FieldValue]:
    """Read the run back; it must hold exactly the words written."""
    spec = rw.spec
    got = (await bus.read(unit, spec.table, spec.address, spec.words,
                          timeout=timing.timeout, retries=timing.retries)).values
    if tuple(got) != rw.words:
        raise VerificationError(f"{spec.label(0)}: wrote {words_to_hex(rw.words)} but it reads "
                                f"back {words_to_hex(got)}")
    n = spec.layout.words
    return [interpret(f, got[i * n:(i + 1) * n]) for i, f in enumerate(spec.fields())]
