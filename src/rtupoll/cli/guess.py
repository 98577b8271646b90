"""``rtupoll guess``: read registers of a device with no profile and rank what they could be.

The read reaches one register further on each side than asked (when the device
allows it), because an off-by-one between the manual and the wire is the most common
reason a value "makes no sense". Offline, ``--words`` takes the registers as hex.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import click

from rtupoll.cli.options import format_option, line_options
from rtupoll.cli.params import UNIT, Seconds
from rtupoll.errors import DeviceException, UsageError
from rtupoll.model.guess import Guess, interpretations, parse_words
from rtupoll.model.raw import SYNTAX, parse_spec
from rtupoll.rtu import Table
from rtupoll.rtu.functions import MAX_REGISTERS
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike

DEFAULT_COUNT = 4  # registers when COUNT is omitted: room for an f64 at START

EPILOG = """\b
Examples:
  rtupoll guess --port /dev/ttyUSB0 --address 1 input:0x0006
  rtupoll guess -p /dev/ttyUSB0 -b 4800 --address 1 input:0x0004:6
  rtupoll guess --words 0000 A0C1                  (offline: registers as hex)
  rtupoll guess --words 0000 A0C1 input:6          (label them from address 6)
"""


@click.command(epilog=EPILOG)
@click.argument("args", nargs=-1, metavar="TABLE:START[:COUNT] | WORD...")
@click.option("--port", "-p", envvar="RTUPOLL_PORT", default=None,
              help="Serial port or tcp://HOST:PORT (not needed with --words).")
@click.option("--address", "-a", "unit", type=UNIT, default=None,
              help="The device's unit address.")
@click.option("--words", "offline", is_flag=True,
              help="The arguments are 16-bit registers in hex, not a register spec: decode "
                   "them offline.")
@click.option("--timeout", type=Seconds(0.01, 30), default=0.5, show_default=True,
              help="Response timeout per request, seconds.")
@click.option("--top", type=int, default=12, show_default=True,
              help="How many interpretations to list (0: all).")
@format_option("table", "json")
@line_options
@click.option("--baudrate", "-b", type=int, default=9600, show_default=True, help="Baud rate.")
@click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False), default="N",
              show_default=True, help="Parity.")
@click.option("--stopbits", type=click.Choice(["1", "2"]), default="1", show_default=True,
              help="Stop bits.")
def guess(args: tuple[str, ...], port: str | None, unit: int | None, offline: bool,
          timeout: float, top: int, fmt: str, baudrate: int, parity: str, stopbits: str
          ) -> None:
    """Rank interpretations of registers from a device that has no profile yet.

    Each position from one register before START to one past the range is read as
    u16, i16, u32, i32, f32, f64 in every byte order (ABCD, BADC, CDAB, DCBA) and as
    text, and ranked: floats with sane exponents and few digits, small integers,
    printable text, and the same reading working for the neighbouring value rank
    high. COUNT (registers) defaults to 4.
    """
    if offline:
        specs = [a for a in args if ":" in a]
        words = parse_words([a for a in args if ":" not in a])
        if not words:
            raise UsageError("--words needs the registers, e.g. --words 0000 A0C1")
        table, start = (_spec(specs[0])[:2]) if specs else (Table.HOLDING, 0)
        first, count = start, len(words)
        source = f"{len(words)} register(s) given"
    else:
        if len(args) != 1:
            raise UsageError(f"give one register range: {SYNTAX}")
        if port is None or unit is None:
            raise UsageError("reading needs --port and --address (or use --words offline)")
        table, start, count = _spec(args[0])
        settings = (port, baudrate, parity.upper(), int(stopbits))
        first, words = _read(settings, unit, table, start, count, timeout)
        source = f"unit {unit}"
    ranked = interpretations(words, first, start, count)
    shown = ranked if top <= 0 else [g for g in ranked if g.score >= 0.1][:top]
    if fmt == "json":
        for g in shown:
            click.echo(to_json(_record(table, g)))
        return
    _table(shown, table, first, words, source, start, count)


def _spec(text: str) -> tuple[Table, int, int]:
    spec = parse_spec(text)
    if not spec.table.is_register:
        raise UsageError("guess interprets registers (input or holding), not bits")
    count = spec.count if text.count(":") >= 2 else DEFAULT_COUNT
    if not 1 <= count <= MAX_REGISTERS:
        raise UsageError(f"COUNT {count} is outside 1..{MAX_REGISTERS} registers")
    return spec.table, spec.address, count


def _read(serial: tuple[str, int, str, int], unit: int, table: Table, start: int,
          count: int, timeout: float) -> tuple[int, tuple[int, ...]]:
    """The registers around START: one more on each side when the device allows it.
    Read on the blocking bus (no event loop), as ``rtupoll read`` does."""
    from rtupoll.cli.target import line_settings, run_on_bus
    from rtupoll.io.serialport import PortSettings

    port, baudrate, parity, stopbits = serial
    # DTR deasserted: some boards (CO2Meter) are held in reset while it is asserted
    settings = PortSettings(port=port, baudrate=baudrate, parity=parity, stopbits=stopbits,
                            deassert_dtr=True, **line_settings())
    tries = [(start - 1, count + 2), (start, count + 1), (start, count)]

    async def job(bus: BusLike) -> tuple[int, tuple[int, ...]]:
        for i, (first, n) in enumerate(t for t in tries
                                       if t[0] >= 0 and t[0] + t[1] <= 0x10000):
            try:
                return first, await bus.read(unit, table, first, n, timeout=timeout, retries=1)
            except DeviceException as exc:
                if exc.code != 2 or i == len(tries) - 1 or (first, n) == (start, count):
                    raise
        raise AssertionError("unreachable")

    return run_on_bus(settings, job, blocking=True)


def _record(table: Table, g: Guess) -> dict[str, object]:
    return {"table": table.value, "address": g.address, "type": g.type, "order": g.order,
            "value": g.value, "words": [f"{w:04X}" for w in g.words], "score": g.score,
            "offset": g.offset, "reasons": list(g.reasons)}


def _table(shown: Sequence[Guess], table: Table, first: int, words: Sequence[int],
           source: str, start: int, count: int) -> None:
    from rich.console import Console
    from rich.table import Table as RichTable

    console = Console()
    console.print(f"{source}, {table.value} 0x{first:04X}..0x{first + len(words) - 1:04X}: "
                  + " ".join(f"{w:04X}" for w in words))
    t = RichTable(title=f"Plausible readings of {table.value} 0x{start:04X}"
                        f"..0x{start + count - 1:04X} (best first)")
    for col in ("#", "address", "type", "order", "value", "score", "why"):
        t.add_column(col, overflow="fold", justify="right" if col in ("#", "score") else "left")
    for i, g in enumerate(shown, 1):
        style = "dim" if g.score < 0.4 else ("bold" if i == 1 else "")
        t.add_row(str(i), f"0x{g.address:04X} ({g.address})", g.type, g.order, g.text,
                  f"{g.score:.2f}", "; ".join(g.reasons), style=style)
    console.print(t)
    if shown:
        best = shown[0]
        order = f", order: {best.order.split('=')[0]}" if best.type not in (
            "u16", "i16", "string") else ""
        length = f", length: {2 * len(best.words)}" if best.type == "string" else ""
        console.print("As a profile field (rename it; check it against a known reading):\n"
                      f"  - {{name: value_{best.address:04x}, table: {table.value}, "
                      f"address: 0x{best.address:04X}, type: {best.type}{length}{order}}}",
                      highlight=False, markup=False)
