"""The sniffer for people: the live per-device table (rich; the one line per transaction
is ``sniff.lines``)."""

from __future__ import annotations

from rich.console import Group, RenderableType
from rich.table import Table
from rich.text import Text

from rtupoll.model.interpret import display
from rtupoll.model.profile import Severity
from rtupoll.sniff.lines import ms
from rtupoll.sniff.model import BusView, Unit

SEVERITY_STYLE = {Severity.OK: "", Severity.INFO: "cyan", Severity.WARNING: "yellow",
                  Severity.ERROR: "bold red"}


def render(view: BusView, now: float, title: str = "") -> RenderableType:
    """The live table: every unit's health and the line's trouble first (what a
    technician sniffing needs most; a short terminal cuts the end), then the latest value
    of each decoded field. No outer border: nothing touches the text."""
    health = Table(title=title or None, title_justify="left", expand=False, pad_edge=False,
                   show_edge=False)
    for name, justify in (("unit", "right"), ("device", "left"), ("req/s", "right"),
                          ("ok", "right"), ("t/o", "right"), ("bad", "right"),
                          ("exc", "left"), ("p50", "right"), ("p95", "right")):
        health.add_column(name, justify=justify)  # type: ignore[arg-type]
    for u in sorted(view.units.values(), key=lambda u: u.unit):
        health.add_row(str(u.unit), _device(u), f"{u.rate(now):.1f}", str(u.ok),
                       _count(u.timeouts, "yellow"), _count(u.garbled, "red"),
                       _exceptions(u), ms(u.p50()), ms(u.p95()))
    fields = Table(expand=False, pad_edge=False, show_edge=False)
    for name in ("device", "field", "value", "unit", "age"):
        fields.add_column(name, justify="right" if name in ("value", "age") else "left")
    for u in sorted(view.units.values(), key=lambda u: u.unit):
        if u.known is None:
            for (table, address), word in sorted(u.image.items(), key=lambda x: (x[0][0].value,
                                                                                   x[0][1]))[:8]:
                fields.add_row(u.name, f"{table.value}:{address}", f"0x{word:04X}", "", "")
            continue
        for f in u.known.profile.fields:
            if f.name in u.failed and (f.name not in u.latest
                                       or u.failed[f.name][0] >= u.latest[f.name][0]):
                when, status = u.failed[f.name]
                last = f" (last {u.latest[f.name][1].text})" if f.name in u.latest else ""
                fields.add_row(u.name, f.name, Text(status + last, style="yellow"), f.unit,
                               _age(now - when))
            elif f.name in u.latest:
                when, fv = u.latest[f.name]
                text, unit = display(fv)  # kelvin as °C, as the poll table shows it
                fields.add_row(u.name, f.name, Text(text, style=SEVERITY_STYLE[fv.severity]),
                               unit, _age(now - when))
    hints = [Text(f"unit {u.unit} looks like {u.hints[0]}", style="cyan")
             for u in sorted(view.units.values(), key=lambda u: u.unit) if u.hints]
    line = Text(f"{view.transactions} transactions; stray bytes {view.noise}, broken frames "
                f"{view.broken}, replies to no request {view.orphans}, broadcasts "
                f"{view.broadcasts}; t/o: timeouts, bad: garbled replies, exc: exceptions "
                "(code x count)", style="dim")
    return Group(health, line, *hints, fields)


def _device(u: Unit) -> Text:
    if u.known is not None:
        return Text(u.known.name)
    if u.hints:
        return Text(f"raw ({u.hints[0].split(' ')[0]}?)", style="cyan")
    return Text("raw", style="dim")


def _count(n: int, style: str) -> Text:
    return Text(str(n), style=style if n else "")


def _exceptions(u: Unit) -> Text:
    if not u.exceptions:
        return Text("0")
    return Text(", ".join(f"{code:02d}x{n}" for code, n in sorted(u.exceptions.items())),
                style="yellow")


def _age(seconds: float) -> str:
    return f"{max(0.0, seconds):.0f} s"
