"""One simulated device: a profile's register map brought to life at an address.

The register image is built from the profile through the same encode path the client
decodes with (``reading.field_words``), so a simulated device answers exactly the map the
profile describes -- and a profile mistake shows up as a disagreement with real peers
such as mbpoll, not as a simulator that agrees with itself.

Behaviour a real device of the profile would show, without naming any device:

- exception 02 outside the map. Registers in a gap between two mapped registers of at
  most ``limits.max_gap`` answer 0: such gaps are undocumented registers inside a table
  the device really has (the Huiwen manual's own example reads across one).
- exception 03 for a count above ``limits.max_registers`` or a malformed write, and for
  a written value outside its field's range or an address the device cannot take.
- exception 02 for writes to a register that is unmapped *or read-only*: the register is
  not a writable address of the device (what most devices answer; the profile's manuals
  do not say).
- exception 01 for functions not in ``limits.functions``. With ``limits.silent_on_error``
  unsupported functions and malformed requests (01 and 03 cases) get no reply at all.
- the ``addresses.any`` id (0xFE) reaches the device whatever its address.
- the variant register (e.g. a data-structure id): default is the newest variant in the
  profile; a variant named in ``variant.on_exception`` answers that exception there and
  hides the fields ``since`` a later variant.
- writing the profile's ``set_address.field`` really moves the device; the reply still
  comes from the old address. ``write_reply`` picks the FC06 reply: ``echo`` (Modbus),
  ``short`` (``unit 06 02 VALUE crc``, the Huiwen manual's frame) or ``none``.
- reading a ``poll: never`` register has its side effect: a peak value resets.
- FC05 on a profile without coil fields (command coils, e.g. a reset) is echoed.
- quirks of a real map the profile does not know (faults ``hole=R`` and ``shift=R``): an
  undocumented hole at register R answers exception 02 to any read over it, even
  inside a bridged gap; a *silent* one is skipped by block reads, which return the
  registers after it shifted down (padded with 0) instead of an exception.
"""

from __future__ import annotations

import dataclasses
import itertools
import random
import struct
from collections.abc import Mapping
from dataclasses import dataclass

from rtupoll.errors import UsageError
from rtupoll.model.codec import Value, decode
from rtupoll.model.interpret import FieldValue, field_words, interpret
from rtupoll.model.profile import Field, Profile
from rtupoll.rtu import Table, with_crc
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.messages import (
    ExceptionReply,
    Malformed,
    OtherReply,
    OtherRequest,
    ReadReply,
    ReadRequest,
    Request,
    WriteMultiple,
    WriteReply,
    WriteSingle,
)
from rtupoll.sim.faults import Fault, FaultSet
from rtupoll.sim.values import Motion, Static, motion_for

WRITE_REPLIES = ("echo", "short", "none")


@dataclass(frozen=True)
class SimDeviceConfig:
    """Everything that makes one simulated device: profile, address and options."""

    profile: Profile
    address: int
    pins: Mapping[str, Value] = dataclasses.field(default_factory=dict)  # never move
    variant: int | None = None
    write_reply: str = "echo"
    turnaround: float | None = None
    faults: tuple[Fault, ...] = ()

    @property
    def name(self) -> str:
        return f"{self.profile.id}@{self.address}"


class SimDevice:
    """The live state of one device: image, motions, address, counters and faults."""

    def __init__(self, config: SimDeviceConfig, *, seed: int = 0, tick: float | None = 1.0,
                 start: float = 0.0) -> None:
        p = self.profile = config.profile
        self.config = config
        self.address = config.address
        self.write_reply = config.write_reply
        self.rng = random.Random(f"{seed}:{p.id}@{config.address}")
        self.faults = FaultSet(config.faults, seed, f"{p.id}@{config.address}")
        self.holes = frozenset(int(f.arg) for f in config.faults
                               if f.kind == "hole" and f.arg is not None)
        self.shifts = frozenset(int(f.arg) for f in config.faults
                                if f.kind == "shift" and f.arg is not None)
        # the silence it needs on the line before it hears a request (fault ``gap=S``)
        self.gap = max((f.arg for f in config.faults if f.kind == "gap" and f.arg is not None),
                       default=0.0)
        self.requests = 0  # requests this device received (its faults count these)
        self.tick, self.start, self.ticks = tick, start, 0
        self.variant, self._exception_at = self._variant(config.variant)
        self.fields = tuple(f for f in p.fields if f.since <= self.variant
                            and (f.table, f.address) not in self._exception_at)
        self.image: dict[Table, dict[int, int]] = {t: {} for t in Table}
        self._by_register: dict[tuple[Table, int], list[Field]] = {}
        for f in self.fields:
            for r in range(f.address, f.end):
                self._by_register.setdefault((f.table, r), []).append(f)
        self.readable = {t: self._readable(t) for t in Table}
        self.address_fields = self._address_fields()
        self.motions: dict[str, Motion] = {}
        for f in self.fields:
            self.motions[f.name] = self._initial_motion(f)
            alone_in_register = len(self._by_register[f.table, f.address]) == 1
            if f.layout.type.value in ("u8", "i8") and alone_in_register:
                # the other byte of the register belongs to no field: give it a visible
                # value, so a write that does not keep it (no read-modify-write) shows
                self.image[f.table][f.address] = self.rng.randint(1, 255) << (
                    0 if f.layout.byte == "high" else 8)
            self._render(f)
        for name, value in config.pins.items():
            self.pin(name, value)

    # -- construction -------------------------------------------------------
    def _variant(self, wanted: int | None) -> tuple[int, dict[tuple[Table, int], int]]:
        var = self.profile.variant
        newest = max((f.since for f in self.profile.fields), default=0)
        variant = newest if wanted is None else wanted
        if var is None:
            return variant, {}
        code = {v: c for c, v in var.on_exception.items()}.get(variant)
        vf = self.profile.field(var.field)
        return variant, ({(vf.table, vf.address): code} if code is not None else {})

    def _readable(self, table: Table) -> frozenset[int]:
        mapped = sorted(r for t, r in self._by_register if t is table)
        out = set(mapped)
        gap = self.profile.limits.max_gap
        for a, b in itertools.pairwise(mapped):
            if 1 < b - a <= gap + 1:
                out.update(range(a + 1, b))
        return frozenset(out)

    def _address_fields(self) -> frozenset[str]:
        p = self.profile
        names = {c.field for c in p.identify if c.equals_address}
        if p.set_address.field:
            names.add(p.set_address.field)
        if not names and any(f.name == "slave_address" for f in self.fields):
            names.add("slave_address")
        return frozenset(n for n in names if any(f.name == n for f in self.fields))

    def _initial_motion(self, f: Field) -> Motion:
        if f.name in self.address_fields:
            return Static(self.address)
        if self.profile.variant and f.name == self.profile.variant.field:
            return Static(self.variant)
        return motion_for(f, self.profile, self.rng)

    def _render(self, f: Field) -> None:
        img = self.image[f.table]
        current = [img.get(r, 0) for r in range(f.address, f.end)]
        words = field_words(f, self.motions[f.name].value, current)
        for r, w in zip(range(f.address, f.end), words, strict=True):
            img[r] = w

    # -- what tests and scenarios use ---------------------------------------
    @property
    def name(self) -> str:
        return f"{self.profile.id}@{self.address}"

    def answers(self, unit: int) -> bool:
        return unit != 0 and unit in (self.address, self.profile.addresses.any)

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        self.profile.field(name)  # raises "no field" with the list of names
        raise UsageError(f"{self.profile.id} field {name} does not exist in "
                         f"{self.profile.variant.name if self.profile.variant else 'variant'} "
                         f"{self.variant}")

    def pin(self, name: str, value: Value) -> None:
        """Fix a field's value (through the codec's encode path); it never moves again."""
        f = self.field(name)
        old = self.motions[f.name]
        self.motions[f.name] = Static(value)
        try:
            self._render(f)
        except Exception:
            self.motions[f.name] = old
            raise

    def value(self, name: str) -> FieldValue:
        f = self.field(name)
        return interpret(f, self.words(f.table, f.address, f.words))

    def words(self, table: Table, address: int, count: int) -> tuple[int, ...]:
        img = self.image[table]
        # from a list, not a generator: tuple(generator) takes a 10-item tuple from the
        # interpreter's free list and shrinks it, so each call parks one more tuple of this
        # size in that free list (up to 2000 a size: ~0.9 MB, filled over 10+ minutes)
        return tuple([img.get(r, 0) for r in range(address, address + count)])

    def advance(self, ticks: int = 1) -> None:
        """Move every unpinned value ``ticks`` steps (what time does, on demand)."""
        moving = [f for f in self.fields if not isinstance(self.motions[f.name], Static)]
        for _ in range(ticks):
            for f in moving:
                self.motions[f.name].step(self.rng)
        for f in moving:
            self._render(f)
        self.ticks += ticks

    def catch_up(self, now: float) -> None:
        """Apply the ticks that elapsed since start (lazily: values only matter when read)."""
        if not self.tick:
            return
        due = int((now - self.start) / self.tick) - self.ticks
        if due > 0:
            self.advance(min(due, 100))
            self.ticks += due - min(due, 100)

    # -- requests -----------------------------------------------------------
    def handle(self, request: Request | Malformed) -> bytes | None:
        """One request (parsed, or refused by the parser) -> the reply frame, or None
        for silence. A malformed request of a function the device supports is answered
        with the parser's exception code, as a device's firmware would."""
        unit, fc = request.unit or 0, request.function or 0
        if isinstance(request, OtherRequest) and (
                (fc == 43 and self.profile.identification) or (fc == 17 and
                                                              self.profile.server_id)):
            return self._identify(request)
        if isinstance(request, OtherRequest) and fc == 8 and 8 in self.profile.limits.functions \
                and request.data[:2] == b"\x00\x00":  # return query data: the request back
            return OtherReply(unit, 8, request.data).frame()
        if fc not in self.profile.limits.functions or fc not in (1, 2, 3, 4, 5, 6, 16):
            return self._refuse(unit, fc, ExceptionCode.ILLEGAL_FUNCTION)
        if isinstance(request, Malformed):
            return self._refuse(unit, fc, request.code or ExceptionCode.ILLEGAL_VALUE)
        if isinstance(request, ReadRequest):
            return self._read(request)
        if isinstance(request, WriteSingle) and fc == 5:
            return self._write_coil(request)
        if isinstance(request, WriteSingle | WriteMultiple):
            return self._write(request)
        # (not reached: fc is 1-6 or 16)
        return self._refuse(unit, fc, ExceptionCode.ILLEGAL_FUNCTION)

    def _identify(self, req: OtherRequest) -> bytes | None:
        """Read device identification (FC 43/14) and report server id (FC 17), as the
        profile documents them."""
        from rtupoll.rtu import identification as ident

        if req.function == 17:
            return with_crc(bytes((req.unit,)) + ident.server_id_reply(self.profile.server_id))
        if len(req.data) != 3 or req.data[0] != ident.MEI_DEVICE_ID:
            return self._refuse(req.unit, 43, ExceptionCode.ILLEGAL_FUNCTION
                                if req.data[:1] != b"\x0e" else ExceptionCode.ILLEGAL_VALUE)
        objects = {o: t.encode("ascii") for o, t in self.profile.identification}
        try:
            pdu = ident.device_id_reply(req.data[1], req.data[2], objects)
        except ValueError:  # an unknown code (3: value), an object it lacks (2: address)
            return self._refuse(req.unit, 43, ExceptionCode.ILLEGAL_ADDRESS if req.data[1] == 4
                                else ExceptionCode.ILLEGAL_VALUE)
        return with_crc(bytes((req.unit,)) + pdu)

    def _refuse(self, unit: int, fc: int, code: int) -> bytes | None:
        if self.profile.limits.silent_on_error and code in (ExceptionCode.ILLEGAL_FUNCTION,
                                                       ExceptionCode.ILLEGAL_VALUE):
            return None
        return ExceptionReply(unit, fc, code).frame()

    def _read(self, req: ReadRequest) -> bytes | None:
        unit, fc, address, count, table = req.unit, req.function, req.address, req.count, \
            req.table
        if table.is_register and count > self.profile.limits.max_registers:
            return self._refuse(unit, fc, ExceptionCode.ILLEGAL_VALUE)
        regs = range(address, address + count)
        for r in regs:
            if (table, r) in self._exception_at:
                return ExceptionReply(unit, fc, self._exception_at[table, r]).frame()
        if any(r not in self.readable[table] for r in regs) or (
                table.is_register and any(r in self.holes for r in regs)) or (
                count == 1 and table.is_register and address in self.shifts):
            return self._refuse(unit, fc, ExceptionCode.ILLEGAL_ADDRESS)
        words = self.words(table, address, count)
        skipped = sorted(r for r in regs if r in self.shifts) if table.is_register else []
        if skipped:  # the silent hole: the registers after it move down, 0 fills the end
            kept = [r for r in range(address, address + count + len(skipped))
                    if r not in self.shifts][:count]
            img = self.image[table]
            words = tuple([img.get(r, 0) for r in kept])
        for f in {f.name: f for r in regs for f in self._by_register.get((table, r), ())}.values():
            if self.motions[f.name].on_read():  # e.g. a peak that reading resets
                self._render(f)
        return ReadReply(unit, fc, words).frame()

    def _write_coil(self, req: WriteSingle) -> bytes | None:
        if any(f.table is Table.COIL for f in self.fields):
            fs = self._by_register.get((Table.COIL, req.address))
            if not fs or not all(f.writable for f in fs):
                return self._refuse(req.unit, req.function, ExceptionCode.ILLEGAL_ADDRESS)
        self.image[Table.COIL][req.address] = req.value
        return WriteReply(req.unit, 5, req.address, req.value).frame()

    def _write(self, req: WriteSingle | WriteMultiple) -> bytes | None:
        unit, fc, address, values = req.unit, req.function, req.address, req.values
        regs = range(address, address + len(values))
        touched: dict[str, Field] = {}
        for r in regs:
            fs = self._by_register.get((Table.HOLDING, r))
            if not fs or not all(f.writable for f in fs):
                return self._refuse(unit, fc, ExceptionCode.ILLEGAL_ADDRESS)
            touched.update((f.name, f) for f in fs)
        new = dict(self.image[Table.HOLDING])
        new.update(zip(regs, values, strict=True))
        decoded: dict[str, Value] = {}
        for f in touched.values():
            value = decode([new.get(r, 0) for r in range(f.address, f.end)], f.layout)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and (
                    (f.minimum is not None and value < f.minimum)
                    or (f.maximum is not None and value > f.maximum)):
                return self._refuse(unit, fc, ExceptionCode.ILLEGAL_VALUE)
            if f.name == self.profile.set_address.field and (
                    not isinstance(value, int) or self.profile.addresses.check(value)):
                return self._refuse(unit, fc, ExceptionCode.ILLEGAL_VALUE)
            decoded[f.name] = value
        self.image[Table.HOLDING] = new
        for name, v in decoded.items():
            self.motions[name] = Static(v)
        moved = decoded.get(self.profile.set_address.field or "")
        if isinstance(moved, int) and moved != self.address:
            self.address = moved
            for name in self.address_fields - decoded.keys():
                self.motions[name] = Static(moved)
                self._render(self.field(name))
        if fc == 16:
            return WriteReply(unit, 16, address, len(values)).frame()
        if self.write_reply == "short":
            return with_crc(struct.pack(">BBBH", unit, 6, 2, values[0]))
        return None if self.write_reply == "none" else \
            WriteReply(unit, 6, address, values[0]).frame()
