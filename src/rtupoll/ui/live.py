"""The poll display: decoded readings coloured by severity, and the health of every bus.

Rendering only: it reads the scheduler's state and builds rich renderables, so the
same code draws the live table, the ``--once`` table and the tests' StringIO
output. Two layouts: one row per field (device, field, value, unit, severity, status,
age, and a trend of the last minutes where the width allows) when the terminal is tall
enough, else one wrapped line of ``field value unit`` per device. Health comes first:
the footer (each bus's load, each device's health) is always drawn whole, and when the
readings do not fit above it they are cut with a line saying how many more there are.
Narrow, no column is dropped: severity and status share one column (a failed read has
no severity), then the device names become rows of their own. A spinner, a scan
counter, ages and a brief highlight on every changed value show a newcomer at once
that the numbers are live. Kelvin temperatures are shown in °C (``interpret.display``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence

from rich.console import Console, ConsoleOptions, Group, RenderableType, RenderResult
from rich.segment import Segment
from rich.table import Table
from rich.text import Text

from rtupoll.io.port_names import gateway
from rtupoll.jobs.scheduler import BusPoller, DevicePoller
from rtupoll.jobs.stats import DeviceStats, Reading, State
from rtupoll.model.interpret import display, display_unit
from rtupoll.model.profile import Field, Severity
from rtupoll.ui.grid import Column, Grid
from rtupoll.ui.trend import BINS, Trend

SEVERITY_STYLE = {Severity.OK: "green", Severity.INFO: "cyan", Severity.WARNING: "yellow",
                  Severity.ERROR: "bold red"}
VALUE_STYLE = {Severity.OK: "bold", Severity.INFO: "bold cyan", Severity.WARNING: "bold yellow",
               Severity.ERROR: "bold red"}
STATE_STYLE = {State.STARTING: "dim", State.ONLINE: "green", State.RETRYING: "yellow",
               State.OFFLINE: "bold red"}
SPINNER = "⠋⠙⠹⠸⠼⠴⠦⠧⠇⠏"
CHANGED_FOR = 0.8  # seconds a changed value stays highlighted
SHORT = {"timeout": "timeout", "garbled": "garbled", "exception": "exception",
         "skipped": "not read", "port": "port lost", "absent": "not present"}


class PollView:
    """Draws the readings and health of some buses; remembers values to show changes."""

    def __init__(self, buses: Sequence[BusPoller], *, title: str = "", live: bool = True,
                 clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time,
                 footers: Sequence[Callable[[], RenderableType | None]] = ()) -> None:
        self.buses, self.title, self.live = buses, title, live
        self.footers = footers  # more footer lines, e.g. the gateway's clients
        self._clock, self._wall = clock, wall
        self._started = clock()
        self._seen: dict[tuple[str, str], tuple[str, float]] = {}  # -> (text, changed at)
        self._widths: dict[str, int] = {}  # column -> the widest text seen (no jitter)
        self._trends: dict[tuple[str, str], Trend] = {}  # numeric fields' last minutes
        self._sampled: dict[tuple[str, str], float] = {}  # -> time of the reading taken

    @property
    def devices(self) -> list[DevicePoller]:
        return [d for b in self.buses for d in b.devices]

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        if not self.live:  # printed once (--once): everything, however long
            yield self.render(width=options.max_width)
            return
        height = options.height or console.height
        width = options.max_width
        free = options.update(height=None)
        head = console.render_lines(self.header(), free) if self.title else []
        foot = console.render_lines(Group(*self._footer(width)), free, pad=False)
        room = height - len(head) - len(foot)
        body = console.render_lines(Group(self.readings_table(width), Text("")), free,
                                    pad=False) if self.full_height() <= height else []
        if not body or len(body) > room:  # (the estimate spares drawing what cannot fit)
            body = console.render_lines(self.compact_table(), free, pad=False)
        if len(body) > room:  # health first: the readings give way, and say so
            cut = len(body) - max(room - 1, 0) if room > 0 else len(body)
            body = body[:max(room - 1, 0)] + ([[Segment(
                f"… {cut} more line{'s' if cut != 1 else ''} of readings: a taller "
                "terminal shows them")]] if room > 0 else [])
        for line in [*head, *body, *foot][:height]:
            yield from line
            yield Segment.line()

    def render(self, *, compact: bool = False, width: int | None = None) -> RenderableType:
        parts: list[RenderableType] = [self.header()] if self.title else []
        parts.append(self.compact_table() if compact else self.readings_table(width))
        if not compact:
            parts.append(Text(""))
        parts += self._footer(width)
        return Group(*parts)

    def _footer(self, width: int | None) -> list[RenderableType]:
        return [self.health_table(width),
                *(f for f in (footer() for footer in self.footers) if f is not None)]

    def full_height(self) -> int:
        """Lines the one-row-per-field layout needs (header, rows, separators, footer)."""
        devices = self.devices
        rows = sum(max(1, len(d.config.fields)) for d in devices)
        return 1 + 2 + rows + len(devices) - 1 + 1 + 2 * len(self.buses) + len(devices)

    # -- header -----------------------------------------------------------------
    def header(self) -> Text:
        devices = self.devices
        online = sum(d.stats.state is State.ONLINE for d in devices)
        scans = sum(d.stats.cycles for d in devices)
        head = Text()
        if self.live:
            spin = SPINNER[int((self._clock() - self._started) * 8) % len(SPINNER)]
            head.append(f"{spin} ", style="bold cyan")
        head.append(self.title, style="bold")
        head.append(f" · {online}/{len(devices)} online",
                    style="green" if online == len(devices) else "yellow")
        head.append(f" · {scans} scan{'s' if scans != 1 else ''}")
        if self.live:
            head.append(f" · {self._clock() - self._started:.0f} s · Ctrl-C stops", style="dim")
        return head

    # -- one row per field ----------------------------------------------------------
    def readings_table(self, width: int | None = None) -> Grid:
        """One row per field. A reading's ``severity`` (what the value means) and its
        ``status`` (whether the read worked) are separate columns, as in JSON. Columns
        whose text changes every scan keep the widest width seen, so nothing jitters.

        Within ``width``: a trend column only where there is room for it; too narrow for
        all, severity and status share one column (lossless: a failed read has no
        severity, a good one has status ok), then each device's name is a row of its
        own above its fields instead of a column."""
        now = self._wall()
        rows: list[tuple[DevicePoller, int, Field, list[Text]]] = []
        for dev in self.devices:
            cfg, st = dev.config, dev.stats
            for i, f in enumerate(cfg.fields):
                r = st.latest.get(f.name)
                text, unit = self._value(cfg.name, f, r, st)
                cells = [Text(f.name), text, Text(unit), _severity(r), _status(r, st)]
                if self.live:
                    good = st.last_good.get(f.name)
                    cells.append(Text(_age(now - good.time) if good else "never",
                                      style="dim" if r is not None and r.ok else "yellow"))
                cells.append(Text(self._trend(cfg.name, f, r, now), style="cyan"))
                rows.append((dev, i, f, cells))
        heads = ["field", "value", "unit", "severity", "status", *(["age"] if self.live
                                                                    else []), "trend"]
        widths = [max([len(h), *(c[k].cell_len for *_, c in rows)])
                  for k, h in enumerate(heads)]
        widths[1] = max(widths[1], self._widths.get("value", 0))
        device_w = max([len("device"), *(len(d.config.name) for d in self.devices)])

        def fits(columns: list[int]) -> bool:
            return width is None or sum(columns) + 3 * (len(columns) - 1) <= width

        merged = not fits([device_w, *widths[:-1]])
        if merged:  # severity and status in one column
            widths[4] = max(widths[3], widths[4])
            del widths[3]
            heads = [h for h in heads if h != "severity"]
            for *_, c in rows:
                c[4] = c[4] if c[4].plain != "ok" or not c[3].plain else c[3]
                del c[3]
        own_rows = not fits([device_w, *widths[:-1]])
        trend = self.live and not own_rows and any(c[-1].plain for *_, c in rows) \
            and fits([device_w, *widths[:-1], max(widths[-1], BINS)])
        if not trend:
            heads.pop()
            for *_, c in rows:
                c.pop()
        columns = ([] if own_rows else [Column("device")]) + [
            Column(h, "right" if h in ("value", "age") else "left",
                   fold=h in ("value", "status"), max_width={"value": 40, "status": 30}.get(h))
            for h in heads]
        grid = Grid(columns)
        for dev, i, _, cells in rows:
            last = i == len(dev.config.fields) - 1
            if own_rows:
                if i == 0:
                    label = self._device_label(dev, 0)
                    if dev.config.name != dev.config.spec:
                        label.append(f" ({dev.config.spec})", style="dim")
                    if self.live and dev.stats.state in (State.RETRYING, State.OFFLINE):
                        label.append(f" {self._next_try(dev)}", style="yellow")
                    grid.add_row(label, *([""] * (len(heads) - 1)))
                grid.add_row(*cells, end_section=last)
            else:
                grid.add_row(self._device_label(dev, i), *cells, end_section=last)
        for k, col in enumerate(columns):
            if col.header in ("value", "status", "age"):
                widest = max((cells[k].cell_len for cells, _ in grid.rows), default=0)
                col.min_width = self._widths[col.header] = max(
                    widest, self._widths.get(col.header, 0))
        return grid

    def _trend(self, device: str, f: Field, r: Reading | None, now: float) -> str:
        """The field's sparkline; a new numeric reading is added to its window first."""
        key = (device, f.name)
        fv = r.value if r is not None else None
        if r is not None and fv is not None and fv.present and not f.enum and not f.flags \
                and isinstance(fv.value, (int, float)) and not isinstance(fv.value, bool) \
                and self._sampled.get(key) != r.time:
            self._sampled[key] = r.time
            self._trends.setdefault(key, Trend()).add(r.time, float(fv.value))
        trend = self._trends.get(key)
        return trend.line(now) if trend is not None else ""

    def _device_label(self, dev: DevicePoller, line: int) -> Text:
        cfg, st = dev.config, dev.stats
        lines = [Text(cfg.name, style="bold " + STATE_STYLE[st.state])]
        if cfg.name != cfg.spec:
            lines.append(Text(cfg.spec, style="dim"))
        if self.live and st.state in (State.RETRYING, State.OFFLINE):
            lines.append(Text(self._next_try(dev), style="yellow"))
        return lines[line] if line < len(lines) else Text("")

    def _next_try(self, dev: DevicePoller) -> str:
        wait = dev.next_due - self._clock()
        return f"{dev.stats.state.value}, next try in {wait:.0f} s" if wait >= 1 else \
            f"{dev.stats.state.value}, trying"

    # -- one wrapped line per device --------------------------------------------------
    def compact_table(self) -> Table:
        """One wrapped line of readings per device, for a short terminal: no header row,
        and a device's state under its name only when it is not online (the name's
        colour and the footer say it too), so two buses still fit 80x24."""
        t = Table(show_edge=False, pad_edge=False, header_style="bold", show_lines=False,
                  box=None, padding=(0, 1, 0, 0), show_header=False)
        width = max(len(d.config.name) for d in self.devices) + 1
        t.add_column("device", no_wrap=True, min_width=width)
        t.add_column("readings", ratio=1)
        for dev in self.devices:
            cfg, st = dev.config, dev.stats
            label = Text(cfg.name, style="bold " + STATE_STYLE[st.state])
            if st.state is not State.ONLINE:
                label.append(f"\n{st.state.value}", style=STATE_STYLE[st.state])
            latest = [st.latest.get(f.name) for f in cfg.fields]
            if latest and all(r is not None and not r.ok for r in latest):
                # nothing read: one line saying why, not a row of dashes
                why = next((r for r in latest if r is not None and r.status != "skipped"),
                           latest[0])
                assert why is not None
                text = Text(f"{SHORT.get(why.status, why.status)}: {why.error}", style="red")
                text.append(f" ({len(latest)} fields not read)", style="dim red")
                if st.state in (State.RETRYING, State.OFFLINE):
                    text.append(f"\n{self._next_try(dev)}", style="yellow")
                t.add_row(label, text)
                continue
            chips = []
            for f in cfg.fields:
                r = st.latest.get(f.name)
                chip = Text(f.name + " ", style="dim")
                text, unit = self._value(cfg.name, f, r, st)
                chip.append_text(text)
                if unit and r is not None and r.ok:
                    chip.append(" " + unit, style="dim")
                if r is not None and not r.ok:
                    chip.append(f" {_why(r)}", style="red")
                chips.append(chip)
            t.add_row(label, _Chips(chips))
        return t

    # -- cells ----------------------------------------------------------------------
    def _value(self, device: str, f: Field, r: Reading | None, st: DeviceStats
               ) -> tuple[Text, str]:
        """The value as shown (highlighted a moment when it changed) and its unit."""
        if r is None:
            return Text("…", style="dim"), display_unit(f)
        if r.value is None:
            return Text("—", style="dim red"), display_unit(f)
        fv = r.value
        text, unit = display(fv)
        key, now = (device, f.name), self._clock()
        before = self._seen.get(key)
        changed_at = now if before is not None and before[0] != text else (
            before[1] if before else -CHANGED_FOR)
        self._seen[key] = (text, changed_at)
        style = VALUE_STYLE[fv.severity]
        if self.live and now - changed_at < CHANGED_FOR:
            style += " reverse"
        return Text(text, style=style), unit

    # -- footer -----------------------------------------------------------------------
    def health_table(self, width: int | None = None) -> Group:
        """Each bus's line and its devices' health. Narrower than 90 columns, counter
        columns that are 0 for every device (late, garbled) are left out, so the rest
        fits 80 columns whole."""
        now, wall = self._clock(), self._wall()
        parts: list[RenderableType] = []
        for bus in self.buses:
            b = bus.config
            load = bus.load.utilisation(now)
            line = Text("bus ", style="bold")
            line.append(b.name, style="bold")
            if b.name != b.port:
                line.append(f" ({b.port})", style="dim")
            if gateway(b.port) is None:
                line.append(f" · {b.serial_text}")
            if self.live:  # one scan's load says nothing about the bus: only live
                line.append(f" · busy {load:.0%}", style="bold yellow" if load > 0.9 else "")
                line.append(f" · {bus.load.rate(now):.0f} transactions/s")
            if bus.port_error:
                line.append(f" · {bus.port_error}", style="bold red")
            if bus.transport.echo_found:  # (Line.adopt_echo)
                line.append(" · the adapter echoes: add --echo", style="bold yellow")
            parts.append(line)
            heads = ("  device", "state", "ok", "retried", "timeout", "late", "garbled",
                     "except", "p50", "p95", "waits", "gap", "last ok")
            rows: list[list[Text | str]] = []
            for dev in bus.devices:
                st = dev.stats
                rows.append([
                    Text("  " + dev.config.name),
                    Text(st.state.value, style=STATE_STYLE[st.state]),
                    str(st.ok), _count(st.retried, style="yellow"), _count(st.timed_out),
                    _count(st.late), _count(st.garbled_attempts),
                    _count(st.exception_count, _codes(st.exceptions.items())),
                    _ms(st.p50()), _ms(st.p95()), _wait(st.timeout, st.timeout_source),
                    _gap(st.idle_gap, st.gap_source),
                    _age(wall - st.last_good_time) if st.last_good_time else "never",
                ])
            keep = [i for i, h in enumerate(heads)
                    if (h != "gap" or any(str(r[i]) != "—" for r in rows))
                    and (width is None or width >= 90 or h not in ("retried", "late", "garbled")
                         or any(str(r[i]) != "0" for r in rows))]
            natural = sum(max([len(heads[i]), *(len(str(r[i])) for r in rows)]) + 1
                          for i in keep)
            short = width is not None and natural > width
            if short:  # every column stays: shorter names, times in ms without the unit
                names = dict(zip(heads, SHORT_HEADS, strict=True))
                rows = [[_bare_ms(c) for c in r] for r in rows]
            grid = Grid([Column(names[heads[i]] if short else heads[i],
                                "left" if heads[i] in ("  device", "state") else "right")
                         for i in keep], header_style="dim", lines=False)
            for r in rows:
                grid.add_row(*(r[i] for i in keep))
            parts.append(grid)
            if short:
                told = [f"{names[heads[i]]} {heads[i]}" for i in keep
                        if heads[i] in ("retried", "timeout", "garbled", "except")]
                parts.append(Text(f"  {', '.join(told).replace('except', 'exception')}; "
                                  "times in ms", style="dim"))
            for dev in bus.devices:  # registers learned never to bridge (jobs.holes)
                for note in dev.stats.holes:
                    parts.append(Text(f"  {dev.config.name}: not bridged: {note}",
                                      style="dim"))
        return Group(*parts)


class _Chips:
    """``field value unit`` chips packed into lines, never broken inside a chip."""

    def __init__(self, chips: Sequence[Text]) -> None:
        self.chips = chips

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        width = options.max_width
        line, out = Text(), []
        for chip in self.chips:
            if line.cell_len and line.cell_len + 2 + chip.cell_len > width:
                out.append(line)
                line = Text()
            if line.cell_len:
                line.append("  ")
            line.append_text(chip)
        out.append(line)
        yield Text("\n").join(out)

    def __rich_measure__(self, console: Console, options: ConsoleOptions) -> object:
        from rich.measure import Measurement

        widest = max((c.cell_len for c in self.chips), default=1)
        return Measurement(min(widest, options.max_width), options.max_width)


def _severity(r: Reading | None) -> Text:
    """What the value means: ok, info, warning, error (or an undocumented code)."""
    if r is None or r.value is None:
        return Text("")
    fv = r.value
    label = fv.severity.value
    if fv.field.enum and fv.code is not None and fv.code not in fv.field.enum \
            and fv.field.other is None:
        label = "unknown code"
    return Text(label, style=SEVERITY_STYLE[fv.severity])


def _status(r: Reading | None, st: DeviceStats) -> Text:
    """Whether the read worked: ok, timeout, exception 02, not present, ..."""
    if r is None:
        return Text(st.state.value, style="dim")
    if r.value is None:
        style = {"skipped": "dim red", "absent": "dim"}.get(r.status, "red")
        return Text(_why(r), style=style)
    return Text("ok", style="green")


def _why(r: Reading) -> str:
    """A failed reading's status in a few words: 'timeout', 'exception 02', ..."""
    if r.status == "exception" and "exception " in r.error:
        return "exception " + r.error.split("exception ", 1)[1].split()[0]
    return SHORT.get(r.status, r.status)


SHORT_HEADS = ("  device", "state", "ok", "rtr", "t/o", "late", "bad", "exc", "p50", "p95",
               "wait", "gap", "last ok")


def _bare_ms(cell: Text | str) -> Text | str:
    """``12 ms`` -> ``12`` (the legend says ms), keeping a Text's style."""
    if isinstance(cell, Text) and cell.plain.endswith(" ms"):
        return Text(cell.plain[:-3], style=cell.style)
    if isinstance(cell, str) and cell.endswith(" ms"):
        return cell[:-3]
    return cell


def _codes(items: Iterable[tuple[int, int]]) -> str:
    return " ".join(f"{n}×{code:02d}" for code, n in sorted(items))  # noqa: RUF001


def _count(n: int, detail: str = "", style: str = "red") -> Text:
    return Text(detail or str(n), style=style if n else "dim")


def _gap(seconds: float, source: str) -> Text:
    """The idle gap a device waits for: set (plain), learned (``~``); none: —."""
    if not seconds:
        return Text("—", style="dim")
    return Text(f"{'~' if source == 'learned' else ''}{seconds * 1000:.0f} ms",
                style="yellow" if source == "learned" else "")


def _ms(seconds: float | None) -> str:
    return "—" if seconds is None else f"{seconds * 1000:.0f} ms"


def _wait(seconds: float | None, source: str) -> Text:
    """The timeout a device gets now: learned (plain), the profile's (dim), pinned (=)."""
    if seconds is None:
        return Text("—")
    if source == "pinned":
        return Text(f"={seconds * 1000:.0f} ms")
    return Text(f"{seconds * 1000:.0f} ms", style="dim" if source == "profile" else "")


def _age(seconds: float) -> str:
    if seconds < 60:
        return f"{max(0.0, seconds):.1f} s"
    if seconds < 3600:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
