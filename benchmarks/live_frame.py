"""One frame of the live poll table: its CPU drawn by rtupoll (``rtupoll.ui.grid``)
against rich's own ``Table`` drawing the same view, in the same run.

The view is the demo's five devices after two real scans of a simulated bus, drawn
to a terminal (ANSI colours, as ``poll`` draws on one) at the sizes given, each
frame the whole screen as ``Live`` writes it. Both ways draw the same characters in
the same styles (tests/ui/test_grid.py); they alternate, round after round, so a
machine that gets busier or quieter affects both alike.

Run: .venv/bin/python benchmarks/live_frame.py [--frames 40] [--rounds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import io
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager

from rich.console import Console

from rtupoll.config.site import from_specs
from rtupoll.jobs.scheduler import BusPoller, Scheduler
from rtupoll.sim.runner import simulated_bus
from rtupoll.ui.grid import Grid
from rtupoll.ui.live import PollView

DEMO = ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
        "banner-ez-array@5"]
SIZES = [(120, 50), (100, 50), (80, 24)]  # one row per field (trend, then without); compact


def scanned() -> list[BusPoller]:
    with simulated_bus(DEMO, baudrate=115200) as bus:
        specs = [(s.split("@")[0], int(s.split("@")[1])) for s in DEMO]
        scheduler = Scheduler(from_specs(bus.port, specs, baudrate=115200, timeout=0.1,
                                         check_serial=False))

        async def scans() -> None:
            await scheduler.open()
            try:
                for _ in range(2):
                    await scheduler.scan_once(lambda d, r: None)
            finally:
                await scheduler.close()

        asyncio.run(scans())
    return scheduler.buses


@contextmanager
def riches() -> Iterator[None]:
    """Every Grid drawn by rich's Table instead."""
    own = Grid.__rich_console__
    Grid.__rich_console__ = lambda self, console, options: iter([self.table()])  # type: ignore[method-assign]
    try:
        yield
    finally:
        Grid.__rich_console__ = own  # type: ignore[method-assign]


def frame_ms(view: PollView, width: int, height: int, frames: int) -> float:
    out = io.StringIO()
    console = Console(file=out, width=width, height=height, color_system="256",
                      force_terminal=True)
    started = time.process_time()
    for _ in range(frames):
        console.print(view)
        out.seek(0)
        out.truncate()
    return (time.process_time() - started) / frames * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    view = PollView(scanned(), title="simulated: demo")
    print(f"{'terminal':>9} {'rtupoll':>9} {'rich Table':>11} {'ratio':>6}")
    for width, height in SIZES:
        ours, theirs = [], []
        for _ in range(args.rounds):
            ours.append(frame_ms(view, width, height, args.frames))
            with riches():
                theirs.append(frame_ms(view, width, height, args.frames))
        a, b = statistics.median(ours), statistics.median(theirs)
        print(f"{width:>5}x{height:<3} {a:>6.1f} ms {b:>8.1f} ms {a / b:>6.2f}")


if __name__ == "__main__":
    main()
