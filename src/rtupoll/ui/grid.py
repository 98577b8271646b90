"""A table drawn as rich's ``Table`` draws it, at a fraction of the cost.

rich measures, pads and renders every cell of a ``Table`` anew on every frame: the live
poll table of the five demo devices took 32 ms a frame here, four frames a second (a
Raspberry Pi is several times slower). ``Grid`` holds the same columns and rows and
draws the same lines, character for character and style for style
(``tests/ui/test_grid.py`` compares them), as one ``Text`` a line, whenever every cell
fits its column on one line and the columns fit the width; otherwise it hands the
table to rich (``table()``), which folds long cells and shrinks columns.

Two looks, the live display's: with ``lines``, no outer edge, a heavy rule under the
header, a light one between sections, one space between a cell and a column line;
without, one space between columns and nothing else.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

from rich.cells import cell_len
from rich.console import Console, ConsoleOptions, RenderResult
from rich.table import Table
from rich.text import Text


@dataclasses.dataclass
class Column:
    header: str
    justify: Literal["left", "right"] = "left"
    fold: bool = False  # long text goes on over more lines (else it is cut with "…")
    max_width: int | None = None
    min_width: int | None = None


class Grid:
    """Columns, then rows of cells (``add_row``), as ``rich.table.Table`` takes them."""

    def __init__(self, columns: Sequence[Column], *, header_style: str = "bold",
                 lines: bool = True) -> None:
        self.columns = list(columns)
        self.header_style, self.lines = header_style, lines
        self.rows: list[tuple[list[Text], bool]] = []

    def add_row(self, *cells: Text | str, end_section: bool = False) -> None:
        self.rows.append(([c if isinstance(c, Text) else Text(c) for c in cells],
                          end_section))

    def table(self) -> Table:
        """rich's table of these columns and rows."""
        t = Table(show_edge=False, pad_edge=False, header_style=self.header_style) \
            if self.lines else Table(show_edge=False, pad_edge=False, box=None,
                                     padding=(0, 1, 0, 0), header_style=self.header_style)
        for c in self.columns:
            t.add_column(c.header, justify=c.justify, no_wrap=not c.fold,
                         overflow="fold" if c.fold else "ellipsis", max_width=c.max_width,
                         min_width=c.min_width)
        for cells, end_section in self.rows:
            t.add_row(*cells, end_section=end_section)
        return t

    def widths(self, room: int) -> list[int] | None:
        """Each column's width as rich makes it, where the grid draws itself in ``room``
        columns; None where rich draws it (no rows, a cell that does not fit its column
        on one line, or columns wider than the room)."""
        out = []
        for i, c in enumerate(self.columns):
            column = [row[i] for row, _ in self.rows]
            if any("\n" in cell.plain for cell in column):
                return None
            width = max([cell_len(c.header), c.min_width or 0, *(cell.cell_len for cell in column)])
            if c.max_width is not None and width > c.max_width:
                return None
            out.append(width)
        gaps = (3 if self.lines else 1) * (len(out) - 1)
        return out if self.rows and sum(out) + gaps <= room else None

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        widths = self.widths(options.max_width)
        if widths is None:
            yield self.table()
            return
        bold = self.header_style  # (the header's padding too, not its column line)
        head = [Text(c.header, style=bold) for c in self.columns]
        if not self.lines:
            yield self._line(head, widths, Text(" ", style=bold))
            for cells, _ in self.rows:
                yield self._line(cells, widths, Text(" "))
            return
        yield self._line(head, widths, Text.assemble((" ", bold), "┃", (" ", bold)))
        yield self._rule(widths, "━", "╇")
        for n, (cells, end_section) in enumerate(self.rows):
            yield self._line(cells, widths, Text(" │ "))
            if end_section and n < len(self.rows) - 1:
                yield self._rule(widths, "─", "┼")

    def _line(self, cells: Sequence[Text], widths: Sequence[int], between: Text) -> Text:
        line = Text(no_wrap=True, overflow="crop")
        for i, (cell, c, width) in enumerate(zip(cells, self.columns, widths, strict=True)):
            if i:
                line.append_text(between)
            cell = cell.copy()  # padded in its own style, as rich pads it
            if c.justify == "right":
                cell.rstrip()
                cell.pad_left(width - cell.cell_len)
            else:
                cell.pad_right(width - cell.cell_len)
            line.append_text(cell)
        return line

    @staticmethod
    def _rule(widths: Sequence[int], dash: str, cross: str) -> Text:
        last = len(widths) - 1
        return Text(cross.join(dash * (w + (i > 0) + (i < last)) for i, w in enumerate(widths)),
                    no_wrap=True, overflow="crop")
