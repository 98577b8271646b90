"""``rtupoll read``: fields by name (or raw registers) from one device, once.

Run by people checking a wire and by scripts, so the JSON/CSV paths import only
what they print (no rich, no simulator, no scheduler: see ``benchmarks/``), and
every failure is one line with a distinct exit code.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from rtupoll.cli.options import format_option, port_options, profiles_option
from rtupoll.cli.target import (
    Target,
    load_target,
    need_port,
    port_settings,
    run_on_bus,
    speed_note,
    timing_options,
)
from rtupoll.errors import RefusedError, UsageError
from rtupoll.jobs.device import Timing
from rtupoll.jobs.device import timing as device_timing
from rtupoll.model.codec import ByteOrder, words_to_hex
from rtupoll.model.interpret import FieldValue, display, display_unit, interpret
from rtupoll.model.profile import Addressing, Field, Poll, Profile
from rtupoll.model.record import READ_KEYS, record
from rtupoll.rtu.functions import MAX_REGISTERS

if TYPE_CHECKING:
    from rtupoll.model.raw import RegisterSpec

F = TypeVar("F", bound=Callable[..., object])
TYPES = ["u16", "i16", "u32", "i32", "u64", "i64", "f32", "f64", "string"]
SEVERITY_STYLE = {"ok": "", "info": "cyan", "warning": "yellow", "error": "bold red"}

Row = tuple[Field, FieldValue | None, str]  # field, its value (None: not present), why not


def raw_options(f: F) -> F:
    """How raw register specs are written and decoded (read and write share these)."""
    for opt in reversed([
        click.option("--raw", is_flag=True,
                     help="Access registers, not profile fields: each ITEM is "
                          "TABLE:START[:COUNT] and DEVICE may be a bare ADDRESS."),
        click.option("--wire", "addressing", flag_value="pdu", default=True,
                     help="--raw START is the address sent on the wire (default; also what "
                          "'direct' manuals print, e.g. 30006 sent as 0x7536)."),
        click.option("--one-based", "addressing", flag_value="one_based",
                     help="--raw START is a 1-based register number (wire = START - 1)."),
        click.option("--modicon", "addressing", flag_value="modicon",
                     help="--raw START is a Modicon reference, 3xxxx input / 4xxxx holding "
                          "(wire = reference - 30001/40001); the table may be left out."),
        click.option("--type", "type_name", type=click.Choice(TYPES), default="u16",
                     show_default=True, help="--raw value type; COUNT counts values of it."),
        click.option("--order", type=click.Choice([o.value for o in ByteOrder],
                                                  case_sensitive=False), default=None,
                     help="--raw byte order of 32/64-bit values (default: the profile's, "
                          "else ABCD)."),
    ]):
        f = opt(f)
    return f


def specs_of(target: Target, items: Sequence[str], addressing: str, type_name: str,
             order: str | None) -> list[RegisterSpec]:
    if not items:
        raise UsageError("--raw needs at least one TABLE:START[:COUNT] (e.g. input:0x0006:2)")
    from rtupoll.model.raw import parse_spec

    # like a profile's own fields: its byte_order is for values wider than one register
    wide = type_name in ("u32", "i32", "u64", "i64", "f32", "f64")
    bo = ByteOrder(order.upper()) if order else (
        target.profile.byte_order if target.profile and wide else ByteOrder.ABCD)
    return [parse_spec(i, addressing=Addressing(addressing), type_name=type_name, order=bo)
            for i in items]


def fields_of(profile: Profile, names: Sequence[str], force: bool) -> list[Field]:
    """The named fields (or the default set); a ``poll: never`` field only with --force."""
    for n in names:
        if ":" in n:
            raise UsageError(f"{n!r} looks like a register spec: add --raw to read registers")
    fields = [profile.field(n) for n in names] if names else list(profile.default_fields())
    for f in fields:
        if f.poll is Poll.NEVER and not force:
            why = f.description or "reading it has side effects"
            raise RefusedError(f"{f.name} is never read unless forced ({why}); add --force to "
                               "read it anyway")
    return fields


@click.command()
@click.argument("device", metavar="DEVICE")
@click.argument("items", nargs=-1, metavar="[FIELD|SPEC]...")
@port_options
@timing_options
@raw_options
@format_option("table", "json", "csv")
@click.option("--hex", "hex_", is_flag=True,
              help="Table: add the registers as read, in hex (json/csv always carry 'raw').")
@click.option("--force", is_flag=True,
              help="Read a field marked 'poll: never' (reading it has side effects).")
@profiles_option
def read(device: str, items: tuple[str, ...], port: str | None, baudrate: int | None,
         parity: str | None, stopbits: str | None, timeout: float | None, retries: int | None,
         raw: bool, addressing: str, type_name: str, order: str | None, fmt: str, hex_: bool,
         force: bool, profile_dirs: tuple[Path, ...]) -> None:
    """Read FIELDs of DEVICE (PROFILE@ADDRESS), or its default fields, once.

    \b
    rtupoll read -p /dev/ttyUSB0 huiwen-aq@1 co2 temperature
    rtupoll read -p /dev/ttyUSB0 --format json net-irnet-pro@1
    rtupoll read -p /dev/ttyUSB0 --raw 5 input:30006:5
    rtupoll read -p /dev/ttyUSB0 --raw --modicon 5 30006:5
    rtupoll read -p /dev/ttyUSB0 --raw --type f32 --order DCBA 1 input:6
    """
    target = load_target(device, profile_dirs, bare_ok=raw)
    port = need_port(port)
    if not raw and target.profile is None:
        raise UsageError("a bare address needs --raw")
    if not raw and (addressing != "pdu" or order or type_name != "u16"):
        raise UsageError("--one-based, --modicon, --type and --order are for --raw reads")
    timing = device_timing(target.profile, timeout, retries)
    if raw:
        specs = specs_of(target, items, addressing, type_name, order)
        max_regs = target.profile.limits.max_registers if target.profile else MAX_REGISTERS
        settings = port_settings(target.profile, port, baudrate, parity, stopbits)
        rows = run_on_bus(settings, lambda bus: read_raw(bus, target.unit, specs, max_regs,
                                                         timing),
                          on_timeout=speed_note(settings, target.profile, baudrate),
                          blocking=True)
    else:
        assert target.profile is not None
        fields = fields_of(target.profile, items, force)
        settings = port_settings(target.profile, port, baudrate, parity, stopbits)
        try:
            rows = run_on_bus(settings, lambda bus: read_named(bus, target, fields, timing),
                              on_timeout=speed_note(settings, target.profile, baudrate),
                              blocking=True)
        except PartialRead as partial:  # every field that answered, then exit 5
            emit(target, partial.rows, fmt, hex_)
            raise partial.error from None
    emit(target, rows, fmt, hex_)


class PartialRead(Exception):
    """Some fields were refused: the rows to print, then ``error`` (exit 5)."""

    def __init__(self, rows: list[Row], error: Exception) -> None:
        super().__init__(str(error))
        self.rows, self.error = rows, error


async def read_named(bus: Any, target: Target, fields: list[Field], timing: Timing
                     ) -> list[Row]:
    """Read through the one read job (``jobs.device.read_fields``): the variant asked
    first where the fields need it, a block refused with exception 02 bisected; every
    field that read is a row, the others say why not."""
    from rtupoll.jobs.device import read_fields

    assert target.profile is not None
    got = await read_fields(bus, target.profile, target.unit, fields, timeout=timing.timeout,
                            retries=timing.retries, probe=True)
    by_name = {fv.field.name: fv for fv in got.values}
    rows = [(f, by_name.get(f.name), got.missing.get(f.name, "")) for f in fields]
    error = got.error()
    if error is not None:  # printed, then exit 5 (refused) or 7 (not scaled)
        raise PartialRead(rows, error)
    return rows


async def read_raw(bus: Any, unit: int, specs: list[RegisterSpec], max_registers: int,
                   timing: Timing) -> list[Row]:
    from rtupoll.model.raw import split_reads

    rows: list[Row] = []
    for spec in specs:
        words: list[int] = []
        for address, count in split_reads(spec, max_registers):
            words += (await bus.read(unit, spec.table, address, count,
                                     timeout=timing.timeout, retries=timing.retries)).values
        n = spec.layout.words
        rows += [(f, interpret(f, words[i * n:(i + 1) * n]), "")
                 for i, f in enumerate(spec.fields())]
    return rows


def records(target: Target, rows: list[Row]) -> list[dict[str, Any]]:
    """One ``output.READ_KEYS`` record per row; a field not present has value null."""
    pid = target.profile.id if target.profile else ""
    out = []
    for f, fv, why in rows:
        if fv is None:
            out.append({"device": target.name, "profile": pid, "address": target.unit,
                        "field": f.name, "value": None, "unit": f.unit, "raw": None,
                        "severity": "info", "text": why})
        else:
            out.append(record(target.name, pid, target.unit, fv))
    return out


def emit(target: Target, rows: list[Row], fmt: str, hex_: bool, title: str = "") -> None:
    if fmt == "json":
        from rtupoll.ui.records import to_json

        for rec in records(target, rows):
            sys.stdout.write(to_json(rec) + "\n")
    elif fmt == "csv":
        from rtupoll.ui.records import CsvWriter

        writer = CsvWriter(sys.stdout, READ_KEYS)
        for rec in records(target, rows):
            writer.write(rec)
    else:
        table(target, rows, hex_, title)
    sys.stdout.flush()


def table(target: Target, rows: list[Row], hex_: bool, title: str = "") -> None:
    """A rich table for people: values coloured by severity, the manual's addresses."""
    from rich.console import Console
    from rich.table import Table as RichTable

    p = target.profile
    raw = (bool(rows) and ":" in rows[0][0].written) or p is None
    heading = title or (f"{target.name} — {p.vendor} {p.model}" if p else
                        f"unit {target.unit} (no profile)")
    if raw and not title:
        heading += ", raw registers"
    t = RichTable()
    t.add_column("field")
    t.add_column("value", justify="right")
    t.add_column("unit")
    t.add_column("address")
    if hex_:
        t.add_column("registers")
    for f, fv, why in rows:
        address = f"{f.table.value} {f.written}"
        if raw:  # the label already says how it was written: show what went on the wire
            address = f"wire 0x{f.address:04X}"
        elif f.layout.type.value in ("u8", "i8"):
            address += f" {f.layout.byte} byte"
        if fv is None:
            cells = [f.name, f"[dim]{why}[/]", display_unit(f), address]
            if hex_:
                cells.append("")
        else:
            style = SEVERITY_STYLE[fv.severity.value]
            text, unit = display(fv)  # kelvin as °C, as the live table shows it
            value = f"[{style}]{_esc(text)}[/]" if style else _esc(text)
            cells = [f.name, value, unit, address]
            if hex_:
                cells.append(words_to_hex(fv.raw) if f.table.is_register
                             else " ".join(str(b) for b in fv.raw))
        t.add_row(*cells)
    console = Console()
    console.print(heading, markup=False, highlight=False)
    console.print(t)


def _esc(text: str) -> str:
    from rich.markup import escape

    return escape(text)
