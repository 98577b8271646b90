"""Fields -> the fewest block reads a device accepts; block words -> decoded fields.

Every request on an RS-485 bus costs two frames, two inter-frame silences and the
device's turnaround, so reading ten adjacent registers in one request instead of
ten is the biggest saving a poller can make. What a device accepts is in its
profile, never in code:

- ``limits.max_registers``: the most registers one read may ask for;
- ``limits.max_gap``: how many unrequested registers a block may read and throw
  away to join two groups of fields (0: only adjacent fields share a request);
- ``field.alone``: the register must be read by a request of its own (some
  devices reject block reads over it), so no other block may include it either;
- ``poll: never``: reading the register has side effects (the Banner's analog peak
  resets when read), so no request touches it -- unless the caller names that very
  field, and then it is read alone, exactly once.

Within one table the blocks are built greedily in address order: a block takes the
next group of fields while the span stays within the limit and the gap is
bridgeable. Every constraint holds for any sub-run of a valid run, so extending as
far as possible gives the fewest blocks (the usual interval-partition exchange
argument); the property tests check the count against that lower bound.

Pure: no I/O, inputs never mutated.
"""

from __future__ import annotations

import functools
from collections.abc import Collection, Iterable, Sequence

from rtupoll.errors import FrameError, RefusedError
from rtupoll.frozen import frozen
from rtupoll.model.interpret import FieldValue, interpret
from rtupoll.model.profile import Field, Poll, Profile
from rtupoll.model.scaling import with_factors
from rtupoll.rtu import Table
from rtupoll.rtu.functions import MAX_BITS

_TABLE_ORDER = {t: i for i, t in enumerate(Table)}


@frozen
class Block:
    """One read request: ``count`` registers (or bits) from ``address`` in ``table``."""

    table: Table
    address: int
    count: int
    fields: tuple[Field, ...]

    @property
    def end(self) -> int:
        """One past the last register read."""
        return self.address + self.count

    @property
    def function(self) -> int:
        return self.table.read_function

    @functools.cached_property
    def interval(self) -> float | None:
        """Seconds between reads of this block's fields when polled (None: every cycle);
        a plan made with ``by_interval`` never mixes fields of different intervals."""
        return min((f.interval for f in self.fields if f.interval is not None), default=None)

    def __str__(self) -> str:
        names = ", ".join(f.name for f in self.fields)
        return f"{self.table.value} 0x{self.address:04X}+{self.count} ({names})"


def for_variant(fields: Iterable[Field], variant: int | None) -> tuple[Field, ...]:
    """Drop fields the device's variant does not have (``since`` above it); None keeps all."""
    return tuple(f for f in fields if variant is None or f.since <= variant)


def read_limit(profile: Profile, table: Table) -> int:
    """Registers (or bits, for coil tables) one read may ask for."""
    return profile.limits.max_registers if table.is_register else MAX_BITS


def plan(fields: Sequence[Field], profile: Profile, *,
         variant: int | None = None, by_interval: bool = False,
         holes: Collection[tuple[Table, int]] = ()) -> tuple[Block, ...]:
    """The fewest block reads covering ``fields`` within ``profile``'s limits.

    The fields a wanted field is scaled by (``scale_by``) are read with it. Fields are
    deduplicated by name; with ``variant`` given, fields newer than it are
    dropped. Blocks come in a stable order (table, then address) so a caller can
    resume a scan at the block that failed. Raises ``RefusedError`` when a field
    cannot be read at all: its function is not supported, it is wider than one read,
    or it shares a register with a ``poll: never`` field it was not asked with.
    With ``by_interval`` (polling), fields with different ``interval`` never share a
    block, so energy totals read every minute do not ride along with power every second.
    ``holes``: registers learned never to bridge for this device (``jobs.holes``: the
    device refused a block over them, or answered it shifted); a field's own registers
    are still read.
    """
    wanted: dict[str, Field] = {}
    for f in for_variant(with_factors(fields, profile), variant):  # factors: scale_by
        wanted.setdefault(f.name, f)
    forbidden = _registers(profile.forbidden())
    learned = frozenset(holes)
    unbridgeable = forbidden | _registers(f for f in profile.fields if f.alone) | learned
    limit_gap = profile.limits.max_gap

    blocks: list[Block] = []
    groups: dict[tuple[Table, float | None], list[Field]] = {}
    for f in wanted.values():
        fn = f.table.read_function
        if fn not in profile.limits.functions:
            raise RefusedError(f"{profile.id} does not implement function {fn} "
                               f"({f.table.value} table) needed to read {f.name}")
        if f.words > read_limit(profile, f.table):
            raise RefusedError(f"{f.name} is {f.words} registers wide, more than "
                               f"{profile.id} reads at once ({read_limit(profile, f.table)})")
        clash = [g.name for g in profile.forbidden() if g.table is f.table
                 and g.address < f.end and f.address < g.end and g.name != f.name]
        if clash:
            raise RefusedError(f"{f.name} shares a register with {clash[0]}, which must "
                               f"never be read (poll: never)")
        if f.alone or f.poll is Poll.NEVER or any((f.table, r) in learned
                                                  for r in range(f.address, f.end)):
            # (a field whose own registers are a learned hole: refused, read alone)
            blocks.append(Block(f.table, f.address, f.words, (f,)))
            continue
        groups.setdefault((f.table, f.interval if by_interval else None), []).append(f)

    for (table, _), members in groups.items():
        limit = read_limit(profile, table)
        run: list[Field] = []
        start = end = 0
        for f in sorted(members, key=lambda g: (g.address, g.end)):
            if run:
                new_end = max(end, f.end)
                gap = range(end, f.address)
                if (len(gap) <= limit_gap and new_end - start <= limit
                        and not any((table, r) in unbridgeable for r in gap)):
                    run.append(f)
                    end = new_end
                    continue
                blocks.append(Block(table, start, end - start, tuple(run)))
            run, start, end = [f], f.address, f.end
        if run:
            blocks.append(Block(table, start, end - start, tuple(run)))

    blocks.sort(key=lambda b: (_TABLE_ORDER[b.table], b.address, b.count))
    return tuple(blocks)


def decode_block(block: Block, words: Sequence[int]) -> list[FieldValue]:
    """The block's fields, interpreted from the registers (or bits) a read returned."""
    if len(words) != block.count:
        raise FrameError(f"{block}: expected {block.count} values, got {len(words)}")
    out = []
    for f in block.fields:
        at = f.address - block.address
        out.append(interpret(f, words[at : at + f.words]))
    return out


def _registers(fields: Iterable[Field]) -> frozenset[tuple[Table, int]]:
    return frozenset((f.table, r) for f in fields for r in range(f.address, f.end))
