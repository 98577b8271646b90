"""``Grid`` draws what rich's ``Table`` of the same columns and rows draws: the same
characters in the same styles, line for line, whatever the cells, styles and width (it
hands over to rich where a cell does not fit its column on one line)."""

from __future__ import annotations

import io
from collections.abc import Callable

from hypothesis import given, settings
from hypothesis import strategies as st
from rich.console import Console, RenderableType
from rich.text import Text
from test_live import SEEDS, scanned

from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.grid import Column, Grid
from rtupoll.ui.live import PollView

Drawn = list[list[tuple[str, str]]]


CONSOLE = Console(file=io.StringIO(), width=200, color_system="truecolor", force_terminal=True)


def drawn(renderable: RenderableType, width: int) -> Drawn:
    """Each line's characters, each with its style (spaces too: a highlighted value's
    padding is highlighted)."""
    options = CONSOLE.options.update_width(width)
    return [[(ch, str(seg.style) if seg.style else "") for seg in line for ch in seg.text]
            for line in CONSOLE.render_lines(renderable, options, pad=False)]


def test_the_live_tables_of_real_scans_at_every_width(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim(*SEEDS, faults=["3:dead", "4:exception=2@2"])
    bus.set(2, "air_gap_cm", 321)
    for unit, flags in ((1, "warning"), (5, "outputs")):  # two flags at once would be
        bus.set(unit, flags, [])  # wider than the value column: rich's, folded, only
    buses = scanned(bus, dead=[3]).buses
    used = set()
    for live in (True, False):
        view = PollView(buses, title="simulated bus", live=live)
        # narrow (rich's, folded), a row for each device's name, severity and status in
        # one column, then all columns and the trend
        for width in (30, 56, 80, 140):
            health = [g for g in view.health_table(width).renderables if isinstance(g, Grid)]
            assert len(health) == len(buses)  # one a bus
            for grid in [view.readings_table(width), *health]:
                assert drawn(grid, width) == drawn(grid.table(), width), width
                used.add(grid.widths(width) is not None)
    assert used == {True, False}  # both ways were drawn: Grid's own, and rich's


styles = st.sampled_from(["", "bold", "dim", "bold green", "bold reverse", "yellow",
                          "red on white"])
words = st.text(st.sampled_from("ab1 .-_µ°³…—"), max_size=14)
span = st.tuples(st.integers(0, 14), st.integers(0, 14), styles)
texts = st.builds(lambda plain, base, part: _styled(plain, base, part), words, styles,
                  st.none() | span)


def _styled(plain: str, base: str, part: tuple[int, int, str] | None) -> Text:
    """A cell: a text in a style, and maybe another style on part of it."""
    text = Text(plain, style=base)
    if part is not None and part[2]:
        text.stylize(part[2], min(part[:2]), max(part[:2]))
    return text


headers = st.text(st.sampled_from("abcµ_ "), min_size=1, max_size=10).filter(str.strip)
columns = st.builds(Column, headers, st.sampled_from(["left", "right"]), st.booleans(),
                    st.none() | st.integers(1, 16), st.none() | st.integers(0, 12))


@settings(max_examples=80)
@given(cols=st.lists(columns, min_size=1, max_size=4), data=st.data(),
       width=st.integers(10, 100), header_style=styles, lines=st.booleans())
def test_any_columns_cells_and_width(cols: list[Column], data: st.DataObject, width: int,
                                     header_style: str, lines: bool) -> None:
    grid = Grid(cols, header_style=header_style, lines=lines)
    for cells in data.draw(st.lists(st.lists(texts, min_size=len(cols), max_size=len(cols)),
                                    max_size=4)):
        grid.add_row(*cells, end_section=data.draw(st.booleans()))
    if grid.widths(width) is not None:  # (else it is rich's table itself)
        assert drawn(grid, width) == drawn(grid.table(), width)
