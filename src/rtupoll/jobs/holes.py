"""Holes in a device's register map: found, remembered, never bridged again.

The planner joins fields across gaps of up to ``limits.max_gap`` registers, because
most devices read an undocumented register in a gap as 0. Some do not, and a manual
rarely says which:

- **a refused block**: the block read over the gap gets exception 02 (illegal data
  address). When every field's own registers still read by themselves, the hole is
  in a gap: ``bisect`` halves the gaps until it has the registers the device refuses
  (a gap whose halves all read is taken whole: what the device refused is bridging
  it). The fields were read meanwhile, so that cycle still has every value.
- **a silent shift**: the block read answers, but the registers after an
  undocumented hole come back shifted (or padded) instead of an exception
  (pysolarfocus#61). Only comparing catches that: ``verify_block`` reads a block and
  each of its fields alone, twice over so a value that moved is not a mismatch, and
  names the fields and addresses that disagree.

Either way the registers go into the device's ``HoleMemory``; the poller re-plans
with them as ``holes`` (``model.planner.plan``), so the gap is never bridged again
for that device. ``HoleStore`` keeps them in a small JSON file next to the site file,
per device, with the profile and the variant they were learned for, so the next run
starts with them (a different profile or variant there starts afresh).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from rtupoll.errors import ConfigError, DeviceException
from rtupoll.model.interpret import FieldValue
from rtupoll.model.planner import Block, decode_block
from rtupoll.model.profile import Field
from rtupoll.rtu import ExceptionCode, Table

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike

Register = tuple[Table, int]
STORE_VERSION = 1


def gaps(block: Block) -> list[range]:
    """The runs of registers ``block`` reads that none of its fields needs."""
    used = {r for f in block.fields for r in range(f.address, f.end)}
    out: list[range] = []
    start: int | None = None
    for r in range(block.address, block.end + 1):
        inside = r < block.end and r not in used
        if inside and start is None:
            start = r
        elif not inside and start is not None:
            out.append(range(start, r))
            start = None
    return out


def pieces(block: Block) -> list[Block]:
    """``block`` cut at its gaps: the fields' own registers, in reads without gaps."""
    out: list[Block] = []
    run: list[Field] = []
    end = 0
    for f in sorted(block.fields, key=lambda g: (g.address, g.end)):
        if run and f.address > end:
            out.append(Block(block.table, run[0].address, end - run[0].address, tuple(run)))
            run = []
        if not run:
            end = f.end
        run.append(f)
        end = max(end, f.end)
    if run:
        out.append(Block(block.table, run[0].address, end - run[0].address, tuple(run)))
    return out


def refused_reading(block: Block) -> str:
    """Why a hole found by bisection is learned: ``exception 02 reading input 0x753A+8``."""
    return f"exception 02 reading {block.table.value} 0x{block.address:04X}+{block.count}"


def show(registers: Iterable[Register]) -> str:
    """``input 0x7540-0x7541, 0x7550``: registers as short ranges."""
    by_table: dict[Table, list[int]] = {}
    for t, r in sorted(registers, key=lambda x: (x[0].value, x[1])):
        by_table.setdefault(t, []).append(r)
    parts = []
    for t, regs in by_table.items():
        spans: list[str] = []
        lo = prev = regs[0]
        for r in [*regs[1:], -1]:
            if r == prev + 1:
                prev = r
                continue
            spans.append(f"0x{lo:04X}" if lo == prev else f"0x{lo:04X}-0x{prev:04X}")
            lo = prev = r
        parts.append(f"{t.value} {', '.join(spans)}")
    return "; ".join(parts)


@dataclass(frozen=True)
class Bisection:
    """What ``bisect`` found: the block's fields that read (without its gaps), the fields
    the device refuses by themselves (with the exception), and the registers not to
    bridge again: refused registers in gaps, and the refused fields' own."""

    values: list[FieldValue]
    holes: frozenset[Register]
    refused: tuple[tuple[Field, DeviceException], ...] = ()


async def bisect(bus: BusLike, unit: int, block: Block, *, timeout: float,
                 retries: int) -> Bisection | None:
    """``block`` got exception 02: find what the device refuses, in the same scan.

    Its fields are read without the gaps (``pieces``); a piece that is refused is split
    between its fields, half by half, until each refused field stands alone (a piece of
    n fields with one refused field costs about 2 log2 n reads). Then the gaps are
    halved down to the registers the device refuses. None when no field reads at all
    (then the exception stands for the whole block). Timeouts and garbled replies
    propagate."""
    values: list[FieldValue] = []
    refused: list[tuple[Field, DeviceException]] = []
    # a piece that is the whole block (no gaps) is known refused: split it at once
    known = DeviceException(ExceptionCode.ILLEGAL_ADDRESS, unit=unit,
                            function=block.table.read_function)
    for piece in pieces(block):
        await _split(bus, unit, piece, values, refused, timeout=timeout, retries=retries,
                     known=known if piece.count == block.count else None)
    if not values:
        return None
    holes: set[int] = set()
    for gap in gaps(block):
        holes |= await _halve(bus, unit, block.table, gap, timeout=timeout, retries=retries)
    if not holes and not refused:  # each gap reads by itself: bridging them was refused
        holes = {r for g in gaps(block) for r in g}
    holes |= {r for f, _ in refused for r in range(f.address, f.end)}
    return Bisection(values, frozenset((block.table, r) for r in holes), tuple(refused))


async def _split(bus: BusLike, unit: int, piece: Block, values: list[FieldValue],
                 refused: list[tuple[Field, DeviceException]], *, timeout: float,
                 retries: int, known: DeviceException | None = None) -> None:
    """Read ``piece`` (fields without gaps); refused (or ``known`` refused): its halves,
    down to one field."""
    try:
        if known is not None:
            raise known
        words = (await bus.read(unit, piece.table, piece.address, piece.count,
                                timeout=timeout, retries=retries)).values
    except DeviceException as exc:
        if len(piece.fields) == 1:
            refused.append((piece.fields[0], exc))
            return
        half = len(piece.fields) // 2
        for part in (piece.fields[:half], piece.fields[half:]):
            start, end = min(f.address for f in part), max(f.end for f in part)
            await _split(bus, unit, Block(piece.table, start, end - start, part), values,
                         refused, timeout=timeout, retries=retries)
        return
    values += decode_block(piece, words)


class FieldsRefused(DeviceException):
    """``rtupoll read``: the device refused some fields with an exception; every other
    field was read and printed (exit 5, like any exception reply)."""

    def __init__(self, refused: Sequence[tuple[Field, DeviceException]]) -> None:
        first = refused[0][1]
        super().__init__(first.code, unit=first.unit, function=first.function)
        names = ", ".join(f.name for f, _ in refused)
        self.args = (f"{names}: {first}; every other field was read",)


async def _halve(bus: BusLike, unit: int, table: Table, span: range, *, timeout: float,
                 retries: int) -> set[int]:
    """The registers of ``span`` the device refuses, by halving."""
    try:
        await bus.read(unit, table, span.start, len(span), timeout=timeout, retries=retries)
        return set()
    except DeviceException:
        if len(span) == 1:
            return {span.start}
    mid = span.start + len(span) // 2
    lo = await _halve(bus, unit, table, range(span.start, mid), timeout=timeout,
                      retries=retries)
    return lo | await _halve(bus, unit, table, range(mid, span.stop), timeout=timeout,
                             retries=retries)


@dataclass(frozen=True)
class Mismatch:
    """A block read that disagrees with its fields read alone: a silent shift."""

    block: Block
    fields: tuple[tuple[Field, tuple[int, ...], tuple[int, ...]], ...]  # (field, block, alone)

    def __str__(self) -> str:
        def words(ws: Sequence[int]) -> str:
            return " ".join(f"{w:04X}" for w in ws)

        parts = [f"{f.name} (0x{f.address:04X}) reads {words(alone)} alone but "
                 f"{words(inblock)} in the block" for f, inblock, alone in self.fields]
        return f"{self.block.table.value} 0x{self.block.address:04X}+{self.block.count}: " + \
            "; ".join(parts)

    def holes(self) -> frozenset[Register]:
        """Where to stop bridging: the gap before the first field that disagrees (or,
        with none right before it, every gap of the block)."""
        first = min(f.address for f, _, _ in self.fields)
        before = [g for g in gaps(self.block) if g.stop == first]
        chosen = before or gaps(self.block)
        return frozenset((self.block.table, r) for g in chosen for r in g)


async def verify_block(bus: BusLike, unit: int, block: Block, *, timeout: float,
                       retries: int, tries: int = 3) -> Mismatch | None:
    """Read ``block``, each field alone, and ``block`` again; a field whose registers
    agree between the two block reads but not with its own read is a mismatch. A value
    that moved meanwhile is read again (up to ``tries`` rounds); still moving: no verdict
    (None). Bus errors propagate."""
    for _ in range(tries):
        first = (await bus.read(unit, block.table, block.address, block.count,
                                timeout=timeout, retries=retries)).values
        alone = {f.name: (await bus.read(unit, f.table, f.address, f.words, timeout=timeout,
                                         retries=retries)).values for f in block.fields}
        second = (await bus.read(unit, block.table, block.address, block.count,
                                 timeout=timeout, retries=retries)).values
        bad, moved = [], False
        for f in block.fields:
            at = f.address - block.address
            a, b = tuple(first[at : at + f.words]), tuple(second[at : at + f.words])
            if a != b:
                moved = True
            elif tuple(alone[f.name]) != a:
                bad.append((f, a, tuple(alone[f.name])))
        if bad:
            return Mismatch(block, tuple(bad))
        if not moved:
            return None
    return None


@dataclass
class HoleMemory:
    """One device's learned holes, with why, for the life of the process (and the store)."""

    registers: set[Register] = field(default_factory=set)
    notes: list[str] = field(default_factory=list)
    # blocks already bisected without finding a hole (a field's own register refused):
    # not bisected again every scan
    tried: set[tuple[Table, int, int]] = field(default_factory=set)

    def learn(self, registers: Iterable[Register], why: str) -> bool:
        """Add ``registers``; True when any was new."""
        new = set(registers) - self.registers
        if not new:
            return False
        self.registers |= new
        self.notes.append(f"{show(new)}: {why}")
        return True


class HoleStore:
    """Learned holes in a small JSON file: per device, with its profile and variant."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._data: dict[str, dict[str, object]] = {}
        if path.exists():
            try:
                raw = json.loads(path.read_text())
                devices = raw["devices"] if raw.get("version") == STORE_VERSION else {}
                if not isinstance(devices, dict):
                    raise TypeError("devices is not a mapping")
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                raise ConfigError(f"{path}: not a holes file rtupoll wrote ({exc}); "
                                  "delete it to start afresh") from None
            self._data = devices

    @staticmethod
    def for_site(site_file: Path) -> HoleStore:
        """The store next to a site file: ``site.yaml`` -> ``site.holes.json``."""
        return HoleStore(site_file.with_name(site_file.stem + ".holes.json"))

    def get(self, device: str, profile: str, variant: int | None) -> set[Register]:
        entry = self._data.get(device)
        if not entry or entry.get("profile") != profile or entry.get("variant") != variant:
            return set()
        regs = entry.get("holes")
        out: set[Register] = set()
        for item in regs if isinstance(regs, list) else []:
            try:
                out.add((Table(item[0]), int(item[1])))
            except (ValueError, TypeError, IndexError):
                continue
        return out

    def put(self, device: str, profile: str, variant: int | None,
            registers: Iterable[Register]) -> None:
        """Record ``device``'s holes and write the file."""
        self._data[device] = {"profile": profile, "variant": variant,
                              "holes": [[t.value, r] for t, r in sorted(
                                  registers, key=lambda x: (x[0].value, x[1]))]}
        self.path.write_text(json.dumps({"version": STORE_VERSION, "devices": self._data},
                                        indent=1) + "\n")
