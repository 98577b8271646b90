"""Raw register specs: ``TABLE:START[:COUNT]`` for devices (or registers) with no profile.

A technician checking a wire often has only the vendor's register table, written in
one of three conventions: the address as sent on the wire (0x0006, or 30006 for
"direct" devices that send the reference literally), a 1-based register number, or
a Modicon 3xxxx/4xxxx reference. Which one is never guessed: the wire address is the
default and the other two need an explicit flag, because guessing wrong reads the
neighbouring register and looks plausible.

Each value of a spec becomes a synthetic :class:`~rtupoll.model.profile.Field`, so raw
reads go through the same ``reading.interpret`` and ``output.record`` as named
fields and print the same JSON/CSV.
"""

from __future__ import annotations

from collections.abc import Sequence

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.model.codec import ByteOrder, DataType, Layout
from rtupoll.model.profile import Addressing, Field, is_modicon_reference
from rtupoll.numbers import parse_int
from rtupoll.rtu import Table
from rtupoll.rtu.functions import MAX_BITS

TABLE_ALIASES: dict[str, Table] = {
    "coil": Table.COIL, "coils": Table.COIL, "co": Table.COIL,
    "discrete": Table.DISCRETE, "di": Table.DISCRETE,
    "input": Table.INPUT, "ir": Table.INPUT,
    "holding": Table.HOLDING, "hr": Table.HOLDING,
}
MODICON_PREFIX: dict[int, Table] = {0: Table.COIL, 1: Table.DISCRETE, 3: Table.INPUT,
                                    4: Table.HOLDING}
SYNTAX = "TABLE:START[:COUNT] (TABLE: coil, discrete, input or holding; e.g. input:0x0006:2)"


@frozen
class RegisterSpec:
    """A run of ``count`` values of one type, starting at wire address ``address``."""

    table: Table
    address: int  # wire address of the first register
    count: int  # values (of ``layout``), not registers
    layout: Layout
    addressing: Addressing  # how the user wrote START, to label values the same way
    start: int = 0  # START as the user wrote it
    hex_labels: bool = False  # START was written in hex: label in hex too

    @property
    def words(self) -> int:
        """Registers (or coils) the spec covers."""
        return self.count * self.layout.words

    def label(self, index: int) -> str:
        """The ``index``-th value's address, written the way the user wrote the start."""
        written = self.start + index * self.layout.words
        if self.addressing is Addressing.MODICON:
            return str(written)
        return f"{self.table.value}:" + (f"0x{written:04X}" if self.hex_labels else str(written))

    def fields(self) -> tuple[Field, ...]:
        """One synthetic field per value, named by its address label."""
        return tuple(
            Field(name=self.label(i), table=self.table,
                  address=self.address + i * self.layout.words, layout=self.layout,
                  written=self.label(i), access="RW" if self.table in (Table.COIL, Table.HOLDING)
                  else "R")
            for i in range(self.count))


def make_layout(type_name: str, order: ByteOrder, table: Table, *, string_words: int = 1
                ) -> Layout:
    """The layout of one raw value; coils and discrete inputs are always bits."""
    if not table.is_register:
        return Layout(DataType.BOOL)
    dtype = DataType(type_name)
    if dtype is DataType.BOOL:
        raise UsageError(f"--type bool is for coils and discrete inputs, not {table.value} "
                         "registers")
    if dtype is DataType.STRING:
        return Layout(dtype, string_words, order)
    return Layout(dtype, dtype.words, order)


def parse_spec(text: str, *, addressing: Addressing = Addressing.PDU, type_name: str = "u16",
               order: ByteOrder = ByteOrder.ABCD) -> RegisterSpec:
    """Parse ``TABLE:START[:COUNT]`` (or ``REFERENCE[:COUNT]`` with Modicon addressing).

    COUNT counts values of ``type_name`` (default 1); for ``string`` it is the text's
    length in registers, read as one value.
    """
    parts = text.strip().split(":")
    table: Table | None = None
    if parts and parts[0].lower() in TABLE_ALIASES:
        table = TABLE_ALIASES[parts.pop(0).lower()]
    elif parts and parts[0][:1].isalpha() and not parts[0].lower().startswith("0x") \
            and not parts[0].lower().endswith("h"):
        from rtupoll.model.names import close_names

        close = close_names(parts[0], TABLE_ALIASES)
        raise UsageError(f"{text!r}: unknown table {parts[0]!r}"
                         + (f" (did you mean {close[0]!r}?)" if close else "")
                         + f"; tables: {', '.join(t.value for t in Table)}")
    if not 1 <= len(parts) <= 2 or not all(parts):
        raise UsageError(f"{text!r} is not a register spec: {SYNTAX}")
    try:
        start = parse_int(parts[0])
        count = parse_int(parts[1]) if len(parts) == 2 else 1
    except ValueError:
        raise UsageError(f"{text!r}: START and COUNT are numbers (decimal or 0x hex)") from None
    if table is None:
        if addressing is not Addressing.MODICON:
            raise UsageError(f"{text!r} names no table: {SYNTAX}; a bare reference like "
                             "30006 needs --modicon")
        table = modicon_table(start, text)
    if addressing is Addressing.MODICON:
        _check_modicon(table, start, text)
    if count < 1:
        raise UsageError(f"{text!r}: COUNT must be at least 1")
    wire = modicon_wire(table, start) if addressing is Addressing.MODICON \
        else addressing.to_wire(table, start)
    if wire < 0:
        hint = " (1-based numbers start at 1)" if addressing is Addressing.ONE_BASED else ""
        raise UsageError(f"{text!r} is below the first register{hint}")
    layout = make_layout(type_name, order, table, string_words=count)
    if layout.type is DataType.STRING:
        count = 1
    spec = RegisterSpec(table, wire, count, layout, addressing, start,
                        hex_labels=parts[0].lower().startswith("0x"))
    if wire + spec.words > 0x10000:
        raise UsageError(f"{text!r} runs past the last register (65535)")
    return spec


def modicon_table(reference: int, text: str) -> Table:
    """The table a Modicon reference names: 0xxxx coils, 1xxxx, 3xxxx, 4xxxx (or 6 digits)."""
    digits = 6 if reference > 49999 else 5
    prefix = reference // 10 ** (digits - 1)
    if prefix not in MODICON_PREFIX:
        raise UsageError(f"{text!r}: {reference} is not a Modicon reference (0xxxx coils, "
                         "1xxxx discrete inputs, 3xxxx input, 4xxxx holding registers)")
    return MODICON_PREFIX[prefix]


def _check_modicon(table: Table, reference: int, text: str) -> None:
    if not is_modicon_reference(table, reference):
        base = table.modicon_base
        raise UsageError(f"{text!r}: {reference} is not a {table.value} reference "
                         f"({base + 1}..{base + 9999})")


def modicon_wire(spec_table: Table, reference: int) -> int:
    """Wire address of a 5- or 6-digit Modicon reference (already checked)."""
    return Addressing.MODICON.to_wire(spec_table, reference)


def split_reads(spec: RegisterSpec, max_registers: int) -> list[tuple[int, int]]:
    """(wire address, count) reads covering the spec, never splitting a value."""
    per_read = MAX_BITS if not spec.table.is_register else max_registers
    step = max(1, per_read // spec.layout.words) * spec.layout.words
    if spec.layout.words > per_read:
        raise UsageError(f"one {spec.layout.type.value} value needs {spec.layout.words} registers,"
                         f" more than the device reads at once ({per_read})")
    out = []
    for offset in range(0, spec.words, step):
        out.append((spec.address + offset, min(step, spec.words - offset)))
    return out


def parse_values(text: str, spec: RegisterSpec) -> list[str]:
    """``V[,V…]``: the values of a raw write, one per value of the spec."""
    values = [v.strip() for v in text.split(",")] if spec.layout.type is not DataType.STRING \
        else [text]
    if any(v == "" for v in values):
        raise UsageError(f"{text!r}: empty value")
    return values


def words_of(values: Sequence[tuple[int, ...]]) -> tuple[int, ...]:
    return tuple(w for v in values for w in v)
