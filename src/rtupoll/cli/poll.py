"""``rtupoll poll``: watch devices on one or more buses, live, or stream their readings.

The command only wires things together: the site (``--config`` or ad-hoc
devices), the scheduler, the display (``rtupoll.ui.live``) and the record writer.
Signals only set an event that the event loop reads, so a stop never lands in
the middle of a write: every line on stdout or in ``--output`` is whole.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import io
import os
import signal
import sys
from collections.abc import AsyncIterator, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import click

from rtupoll.cli.options import format_option, profiles_option
from rtupoll.cli.params import DEVICE, DeviceSpec
from rtupoll.config.site import DEFAULT_INTERVAL, Site, from_specs, load_site
from rtupoll.errors import ScanIncomplete, UsageError
from rtupoll.ui.records import POLL_KEYS, CsvWriter, to_json

if TYPE_CHECKING:
    from rich.console import Console
    from rich.live import Live

    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.services import Service
    from rtupoll.jobs.stats import Reading
    from rtupoll.ui.live import PollView

REFRESH = 0.25  # seconds between redraws of the live table
SIM_BAUDRATE = 115200  # framing assumed on a simulated bus without wire timing


class RecordWriter:
    """JSON lines or CSV, one whole batch per write, flushed: no partial lines, ever."""

    def __init__(self, out: TextIO, fmt: str, *, header: bool = True) -> None:
        self.out, self.fmt = out, fmt
        self._buf = io.StringIO()
        self._csv = CsvWriter(self._buf, POLL_KEYS, header=header) if fmt == "csv" else None

    def write(self, readings: Sequence[Reading]) -> None:
        for r in readings:
            if self._csv is not None:
                self._csv.write(r.record())
            else:
                rec = r.record()
                self._buf.write(to_json({k: rec.get(k) for k in POLL_KEYS}) + "\n")
        text = self._buf.getvalue()
        self._buf.seek(0)
        self._buf.truncate()
        if text:
            self.out.write(text)
            self.out.flush()


@click.command()
@click.argument("devices", nargs=-1, type=DEVICE, metavar="[DEVICE]...")
@click.option("--config", "-c", "config", type=click.Path(dir_okay=False, path_type=Path),
              help="Site file: buses and their devices (see docs/polling.md).")
@click.option("--port", "-p", envvar="RTUPOLL_PORT",
              help="Serial port (/dev/ttyUSB0) or tcp://HOST:PORT, for DEVICEs given here.")
@click.option("--baudrate", "-b", type=click.IntRange(300, 4_000_000), default=None,
              help="Baud rate (default: the devices' profiles, when they agree).")
@click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False),
              default=None, help="Parity (default: the profiles').")
@click.option("--stopbits", type=click.Choice(["1", "2"]), default=None,
              help="Stop bits (default: the profiles').")
@click.option("--interval", "-i", type=click.FloatRange(0, 86_400), default=None,
              help=f"Seconds between scans of each DEVICE [default: {DEFAULT_INTERVAL:g}; "
                   "0: as fast as the bus allows].")
@click.option("--timeout", type=click.FloatRange(0.01, 30), default=None,
              help="Response timeout in seconds for each DEVICE (default: its profile's).")
@click.option("--retries", type=click.IntRange(0, 10), default=None,
              help="Immediate retries per request (default: the profile's).")
@click.option("--fields", "-f", "fields", default=None, metavar="NAME[,NAME...]",
              help="Poll only these fields (each DEVICE polls those it has).")
@click.option("--once", is_flag=True,
              help="Read every device once, print, exit (9 if any device failed).")
@format_option("table", "json", "csv")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Append json/csv records to this file (the table stays on the terminal).")
@click.option("--simulate", is_flag=True,
              help="Poll simulated devices (all five seed devices when no DEVICE is given).")
@click.option("--baud", type=click.IntRange(300, 4_000_000), default=None,
              help="--simulate: take the real wire time at this baud rate.")
@click.option("--fault", "faults", multiple=True, metavar="SPEC",
              help="--simulate: inject a fault, e.g. 3:dead, 4:crc@10%, slow=1@5- "
                   "(repeatable; see 'rtupoll simulate --help').")
@profiles_option
def poll(devices: tuple[DeviceSpec, ...], config: Path | None, port: str | None,
         baudrate: int | None, parity: str | None, stopbits: str | None,
         interval: float | None, timeout: float | None, retries: int | None,
         fields: str | None, once: bool, fmt: str,
         output: Path | None, simulate: bool, baud: int | None, faults: tuple[str, ...],
         profile_dirs: tuple[Path, ...]) -> None:
    """Poll devices and show their decoded readings live.

    \b
    rtupoll poll --simulate                      # five simulated devices, no hardware
    rtupoll poll -p /dev/ttyUSB0 -b 9600 net-irnet-pro@1 huiwen-aq@3
    rtupoll poll -c site.yaml --format json -o readings.jsonl
    rtupoll poll -c site.yaml --once --format csv

    DEVICE is PROFILE@ADDRESS. Stop with Ctrl-C (or SIGTERM): the current line is
    finished, nothing is left half-written, and the exit status is 0.
    """
    services: list[Service] = []  # run beside the scheduler (rtupoll.jobs.services)
    if output is not None and fmt == "table":
        raise UsageError("--output writes json or csv: add --format json or --format csv")
    if (baud or faults) and not simulate:
        raise UsageError("--baud and --fault are for --simulate (a real bus: --baudrate)")
    if simulate:
        if config or port:
            raise UsageError("--simulate makes its own bus: leave out --config and --port")
        with _simulated(devices, baud or baudrate, faults) as (sim_port, specs):
            site = from_specs(sim_port, specs, baudrate=baud or baudrate or SIM_BAUDRATE,
                              interval=DEFAULT_INTERVAL if interval is None else interval,
                              fields=_split(fields), timeout=timeout, retries=retries,
                              profile_dirs=profile_dirs, check_serial=False)
            site = dataclasses.replace(site, buses=tuple(
                dataclasses.replace(b, name="simulated") for b in site.buses))
            title = "simulated bus" + (f", {baud or baudrate} baud" if baud or baudrate
                                       else ", untimed")
            _run(site, once=once, fmt=fmt, output=output, title=title, services=services)
        if fmt == "table" and not once and not faults:
            click.echo("That was a simulated bus. Try --fault 3:dead (a dead device) or "
                       "--baud 9600.\nYour own devices: rtupoll poll -p /dev/ttyUSB0 "
                       "PROFILE@ADDRESS...", err=True)
        return
    if config is not None:
        if devices or port:
            raise UsageError("give either --config or --port with devices, not both")
        if any(v is not None for v in (interval, fields, timeout, retries, baudrate, parity,
                                       stopbits)):
            raise UsageError("--interval, --fields, --timeout, --retries and serial options "
                             "are set per bus and device in the site file")
        site = load_site(config, profile_dirs)
    else:
        if not port:
            raise UsageError("nothing to poll: give --config FILE, or --port PORT and DEVICEs "
                             "(PROFILE@ADDRESS), or --simulate to try it without hardware")
        if not devices:
            raise UsageError(f"name the devices on {port}: PROFILE@ADDRESS... "
                             "(e.g. net-irnet-pro@1)")
        site = from_specs(port, [(d.profile, d.address) for d in devices], baudrate=baudrate,
                          parity=parity, stopbits=int(stopbits) if stopbits else None,
                          interval=DEFAULT_INTERVAL if interval is None else interval,
                          fields=_split(fields), timeout=timeout, retries=retries,
                          profile_dirs=profile_dirs)
    _run(site, once=once, fmt=fmt, output=output,
         title=config.name if config else str(port), services=services)


def _split(fields: str | None) -> list[str]:
    return [f.strip() for f in (fields or "").split(",") if f.strip()]


@contextlib.contextmanager
def _simulated(devices: Sequence[DeviceSpec], baudrate: int | None, faults: Sequence[str]
               ) -> Iterator[tuple[str, list[tuple[str, int]]]]:
    """Start the simulator in-process; yield its port and the devices it serves."""
    from rtupoll.sim.runner import SEED_DEVICES, simulated_bus

    specs = [(d.profile, d.address) for d in devices] or list(SEED_DEVICES)
    with simulated_bus([f"{p}@{a}" for p, a in specs], baudrate=baudrate,
                       faults=tuple(faults)) as sim:
        yield sim.port, specs


def _run(site: Site, *, once: bool, fmt: str, output: Path | None, title: str,
         services: Sequence[Service] = ()) -> None:
    from rich.console import Console

    from rtupoll.jobs.scheduler import Scheduler
    from rtupoll.ui.live import PollView

    scheduler = Scheduler(site)
    console = Console(stderr=fmt != "table" and output is None)
    show_table = fmt == "table" or (output is not None and console.is_terminal)
    with _sink(fmt, output) as writer:
        view = PollView(scheduler.buses, title=title, live=not once)
        if once:
            readings = asyncio.run(_once(scheduler, writer, services))
            if show_table:
                console.print(view.render())
            _report_failures(site, readings)
        else:
            asyncio.run(_forever(scheduler, writer, view if show_table else None, console,
                                 services))


@contextlib.contextmanager
def _sink(fmt: str, output: Path | None) -> Iterator[RecordWriter | None]:
    if fmt == "table":
        yield None
        return
    if output is None:
        try:
            yield RecordWriter(sys.stdout, fmt)
        except BrokenPipeError:  # `rtupoll poll --format json | head`: the reader is done
            with contextlib.suppress(OSError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return
    try:
        fresh = not output.exists() or output.stat().st_size == 0
        with output.open("a", encoding="utf-8", newline="") as fh:
            yield RecordWriter(fh, fmt, header=fresh)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from None


@contextlib.asynccontextmanager
async def _started(scheduler: Scheduler, services: Sequence[Service]) -> AsyncIterator[None]:
    """The ports open and the services running; both closed again however it ends."""
    await scheduler.open()
    running: list[Service] = []
    try:
        for s in services:
            await s.start(scheduler)
            running.append(s)
        yield
    finally:
        for s in reversed(running):
            await s.stop()
        await scheduler.close()


async def _once(scheduler: Scheduler, writer: RecordWriter | None,
                services: Sequence[Service]) -> list[Reading]:
    """One cycle of every device; records in site order once all are in."""
    got: dict[str, list[Reading]] = {}

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        got[dev.config.name] = readings
        for s in services:
            s.on_readings(dev, readings)

    stop = _stop_event()
    async with _started(scheduler, services):
        scan = asyncio.create_task(scheduler.scan_once(sink))
        stopper = asyncio.create_task(stop.wait())
        await asyncio.wait([scan, stopper], return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
        if not scan.done():
            scan.cancel()
            await asyncio.gather(scan, return_exceptions=True)
            raise KeyboardInterrupt
        scan.result()
    readings = [r for d in scheduler.pollers() for r in got.get(d.config.name, [])]
    if writer is not None:
        writer.write(readings)
    return readings


async def _forever(scheduler: Scheduler, writer: RecordWriter | None, view: PollView | None,
                   console: Console, services: Sequence[Service]) -> None:
    from rich.live import Live

    stop = _stop_event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        for s in services:
            s.on_readings(dev, readings)
        if writer is None:
            return
        try:
            writer.write(readings)
        except BrokenPipeError:
            stop.set()
            raise

    async with _started(scheduler, services):
        if view is None:
            await scheduler.run(sink, stop)
            return
        with Live(view, console=console, auto_refresh=False, transient=False,
                  redirect_stdout=False, redirect_stderr=False) as live:
            painter = asyncio.create_task(_paint(live, stop))
            try:
                await scheduler.run(sink, stop)
            finally:
                painter.cancel()
                live.refresh()


async def _paint(live: Live, stop: asyncio.Event) -> None:
    while not stop.is_set():
        live.refresh()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(stop.wait(), REFRESH)


def _stop_event() -> asyncio.Event:
    """An event set by SIGINT or SIGTERM: the loop finishes what it writes, then stops."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    return stop


def _report_failures(site: Site, readings: Sequence[Reading]) -> None:
    """``--once``: one stderr line per device that failed, then exit 9."""
    failed: dict[str, Reading] = {}
    counts: dict[str, int] = {}
    for r in readings:
        if not r.ok and r.status != "absent":  # a field its variant lacks is no failure
            counts[r.device.name] = counts.get(r.device.name, 0) + 1
            if r.device.name not in failed or failed[r.device.name].status == "skipped":
                failed[r.device.name] = r
    for name, r in failed.items():
        d = r.device
        where = f"{name}" + (f" ({d.spec})" if name != d.spec else "")
        click.echo(f"rtupoll: {where}: {r.status}: {r.error} "
                   f"({counts[name]} of {len(d.fields)} fields not read)", err=True)
    if failed:
        total = sum(len(b.devices) for b in site.buses)
        raise ScanIncomplete(f"{len(failed)} of {total} devices failed")
