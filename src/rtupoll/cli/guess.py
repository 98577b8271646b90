"""``rtupoll guess``: read registers of a device with no profile and rank what they could be.

The read reaches one register further on each side than asked (when the device
allows it), because an off-by-one between the manual and the wire is the most common
reason a value "makes no sense". Offline, ``--words`` takes the registers as hex.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import click

from rtupoll.cli.options import format_option, line_options
from rtupoll.cli.params import UNIT, Seconds
from rtupoll.errors import DeviceException, UsageError
from rtupoll.model.guess import Guess, interpretations, parse_words
from rtupoll.model.raw import SYNTAX, parse_spec
from rtupoll.rtu import ExceptionCode, Table
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
  rtupoll guess -p /dev/ttyUSB0 -a 1 input:0x0006 --known -20.0
  rtupoll guess -p /dev/ttyUSB0 net-irnet-pro@1 --known concentration=-20.0
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
@click.option("--known", metavar="[FIELD=]VALUE", default=None,
              help="A value read off the device (its display: 231.4): list the settings "
                   "(start within 2 registers, type, order, scale) that give it. With "
                   "PROFILE@ADDRESS, FIELD=VALUE checks the profile's field.")
@click.option("--top", type=int, default=12, show_default=True,
              help="How many interpretations to list (0: all).")
@format_option("table", "json")
@line_options
@click.option("--baudrate", "-b", type=int, default=None,
              help="Baud rate (default: 9600, or with PROFILE@ADDRESS the profile's).")
@click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False),
              default=None, help="Parity (default: N, or the profile's).")
@click.option("--stopbits", type=click.Choice(["1", "2"]), default=None,
              help="Stop bits (default: 1, or the profile's).")
def guess(args: tuple[str, ...], port: str | None, unit: int | None, offline: bool,
          timeout: float, known: str | None, top: int, fmt: str, baudrate: int | None,
          parity: str | None, stopbits: str | None) -> None:
    """Rank interpretations of registers from a device that has no profile yet.

    Each position from one register before START to one past the range is read as
    u16, i16, u32, i32, f32, f64 in every byte order (ABCD, BADC, CDAB, DCBA) and as
    text, and ranked: floats with sane exponents and few digits, small integers,
    printable text, and the same reading working for the neighbouring value rank
    high. COUNT (registers) defaults to 4.
    """
    given = (baudrate, parity.upper() if parity else None, int(stopbits) if stopbits else None)
    if known is not None:
        return _known(args, known, port, unit, offline, timeout, top, fmt, given)
    if offline:
        table, start, words = _given(args)
        first, count = start, len(words)
        source = f"{len(words)} register(s) given"
    else:
        if len(args) != 1:
            raise UsageError(f"give one register range: {SYNTAX}")
        if port is None or unit is None:
            raise UsageError("reading needs --port and --address (or use --words offline)")
        table, start, count = _spec(args[0])
        settings = (port, given[0] or 9600, given[1] or "N", given[2] or 1)
        first, words = _read(settings, unit, table, start, count, timeout)
        source = f"unit {unit}"
    ranked = interpretations(words, first, start, count)
    shown = ranked if top <= 0 else [g for g in ranked if g.score >= 0.1][:top]
    if fmt == "json":
        for g in shown:
            click.echo(to_json(_record(table, g)))
        return
    _table(shown, table, first, words, source, start, count)


def _known(args: tuple[str, ...], text: str, port: str | None, unit: int | None,
           offline: bool, timeout: float, top: int, fmt: str,
           given: tuple[int | None, str | None, int | None]) -> None:
    """``--known``: the settings that give a value read off the device."""
    from rtupoll.model.known import REACH, parse_known, solve

    name, sep, number = text.rpartition("=")
    want = parse_known(number)
    profile = field = None
    if sep:  # FIELD=VALUE: the field of PROFILE@ADDRESS, its settings checked
        from rtupoll.cli.target import load_target

        devices = [a for a in args if "@" in a]
        if len(devices) != 1 or offline or len(args) != 1:
            raise UsageError("--known FIELD=VALUE takes one PROFILE@ADDRESS (e.g. "
                             "net-irnet-pro@1 --known concentration=-20.0)")
        target = load_target(devices[0])
        profile, unit = target.profile, target.unit
        assert profile is not None
        field = profile.field(name)
        if not field.table.is_register:
            raise UsageError(f"{field.name} is a bit ({field.table.value}): --known solves "
                             "register values")
        table, start = field.table, field.address
    elif offline:
        table, start, words = _given(args)
    else:
        if len(args) != 1 or args[0].count(":") != 1:
            raise UsageError("--known VALUE takes TABLE:START, where the manual says the "
                             f"value is (it searches {REACH} registers either side)")
        table, start, _ = _spec(args[0])
    if want.value == 0:
        raise UsageError("--known 0 tells no setting from another (every type reads "
                         "all-zero registers as 0): use a value that is not 0")
    if offline and not sep:
        first = start
        source = f"{len(words)} register(s) given"
    else:
        if not port or unit is None:
            raise UsageError("reading needs --port and --address (or PROFILE@ADDRESS; "
                             "offline: --words)")
        # from REACH before to an f64's width past REACH after, as the device allows
        tries = [(start - REACH + k, 4 + 2 * REACH - k) for k in range(REACH + 1)]
        ps = profile.serial if profile else None  # the profile's settings unless given
        serial = (port, given[0] or (ps.baudrate if ps else 9600),
                  given[1] or (ps.parity if ps else "N"), given[2] or (ps.stopbits if ps else 1))
        first, words = _read(serial, unit, table, start, 4, timeout, [*tries, (start, 4)])
        source = f"unit {unit}"
    found = solve(words, first, start, want)
    shown = found if top <= 0 else found[:top]
    mine = None
    if field is not None:
        lay = field.layout
        mine = next((s for s in found if (s.address, s.type, s.order, s.scale) == (
            field.address, lay.type, lay.order, lay.scale)), None)
    if fmt == "json":
        for s in shown:
            rec = {"table": table.value, "address": s.address, "offset": s.offset,
                   "type": s.type.value, "order": s.order.value, "scale": s.scale,
                   "value": s.value, "words": [f"{w:04X}" for w in s.words],
                   "score": s.score, "setting": s.setting}
            if field is not None:
                rec["profile"] = s is mine
            click.echo(to_json(rec))
        return
    from rich.console import Console
    from rich.table import Table as RichTable

    console = Console(highlight=False)
    console.print(f"{source}, {table.value} 0x{first:04X}..0x{first + len(words) - 1:04X}: "
                  + " ".join(f"{w:04X}" for w in words), markup=False)
    if not found:
        console.print(f"No setting within {REACH} registers of 0x{start:04X} gives {number}"
                      f" (±{want.tolerance:g}): check the table (input or holding), the "
                      "device's address and the value's unit (kWh or Wh?).", markup=False)
        raise SystemExit(1)
    t = RichTable(title=f"Settings that read {number} near {table.value} 0x{start:04X} "
                        "(likeliest first)")
    for col in ("#", "starts", "setting", "reads", "score"):
        t.add_column(col, overflow="fold", justify="right" if col in ("#", "score") else "left")
    for i, s in enumerate(shown, 1):
        side = "before" if s.offset < 0 else "after"
        where = f"{abs(s.offset)} {side}" if s.offset else "as given"
        mark = "  (the profile's)" if s is mine else ""
        t.add_row(str(i), where, s.setting + mark, s.text, f"{s.score:.2f}",
                  style="bold" if i == 1 else "")
    console.print(t)
    best = found[0]
    if field is not None and profile is not None:
        reads = ("its setting gives it" if mine is not None else
                 f"its setting ({_setting_of(field)}) does not give it")
        console.print(f"{profile.id} {field.name}: {reads}"
                      + ("" if mine is None or mine is best else
                         "; a likelier one does too: a second known value decides"),
                      markup=False)
    else:
        console.print("As a profile field (rename it; check a second known value):\n"
                      f"  - {{name: value_{best.address:04x}, table: {table.value}, "
                      f"{best.setting}}}", markup=False)
    ties = [s for s in found[1:] if s.score == best.score]
    if ties:
        console.print(f"{len(ties)} other setting(s) read it as well: a second known "
                      "value (another field) tells them apart.", markup=False)


def _setting_of(field: Any) -> str:
    from rtupoll.model.known import Solution

    lay = field.layout
    return Solution(field.address, 0, lay.type, lay.order, lay.scale, (), 0.0, 0.0).setting


def _given(args: tuple[str, ...]) -> tuple[Table, int, tuple[int, ...]]:
    """``--words``: the registers in hex, and where they start (TABLE:START, else holding 0)."""
    specs = [a for a in args if ":" in a]
    words = parse_words([a for a in args if ":" not in a])
    if not words:
        raise UsageError("--words needs the registers, e.g. --words 0000 A0C1")
    table, start = (_spec(specs[0])[:2]) if specs else (Table.HOLDING, 0)
    return table, start, words


def _spec(text: str) -> tuple[Table, int, int]:
    spec = parse_spec(text)
    if not spec.table.is_register:
        raise UsageError("guess interprets registers (input or holding), not bits")
    count = spec.count if text.count(":") >= 2 else DEFAULT_COUNT
    if not 1 <= count <= MAX_REGISTERS:
        raise UsageError(f"COUNT {count} is outside 1..{MAX_REGISTERS} registers")
    return spec.table, spec.address, count


def _read(serial: tuple[str, int, str, int], unit: int, table: Table, start: int,
          count: int, timeout: float, tries: list[tuple[int, int]] | None = None
          ) -> tuple[int, tuple[int, ...]]:
    """The registers around START: one more on each side when the device allows it.
    Read on the blocking bus (no event loop), as ``rtupoll read`` does."""
    from rtupoll.cli.target import line_settings, run_on_bus
    from rtupoll.io.port_settings import PortSettings

    port, baudrate, parity, stopbits = serial
    # DTR deasserted: some boards (CO2Meter) are held in reset while it is asserted
    settings = PortSettings(port=port, baudrate=baudrate, parity=parity, stopbits=stopbits,
                            deassert_dtr=True, **line_settings())
    tries = tries or [(start - 1, count + 2), (start, count + 1), (start, count)]

    async def job(bus: BusLike) -> tuple[int, tuple[int, ...]]:
        for i, (first, n) in enumerate(t for t in tries
                                       if t[0] >= 0 and t[0] + t[1] <= 0x10000):
            try:
                return first, (await bus.read(unit, table, first, n, timeout=timeout,
                                              retries=1)).values
            except DeviceException as exc:
                if exc.code != ExceptionCode.ILLEGAL_ADDRESS or i == len(tries) - 1 \
                        or (first, n) == (start, count):
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
