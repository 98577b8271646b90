"""One run of ``rtupoll poll``: the scheduler, its services, the live table and the
records, from start to end, and its outcome.

``cli/poll.py`` turns the command's options into a ``PollRun`` and the ``Outcome`` into
an exit status; everything between is here. Signals only set an event that the event
loop reads (``stop``), so a stop never lands in the middle of a write: every line on
stdout or in ``--output`` is whole.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from rtupoll import aio
from rtupoll.errors import UsageError
from rtupoll.ui.outfile import OutputFile
from rtupoll.ui.pipe_writer import PipeWriter, threaded, unread
from rtupoll.ui.record_writer import RecordWriter

if TYPE_CHECKING:
    from rich.console import Console
    from rich.live import Live

    from rtupoll.config.http_settings import HttpSettings
    from rtupoll.config.site import Site
    from rtupoll.gateway.service import GatewayService
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.services import Service
    from rtupoll.jobs.stats import Reading
    from rtupoll.ui.live import PollView
    from rtupoll.ui.records import RecordFormat

REFRESH = 0.25  # seconds between redraws of the live table


@dataclass
class PollRun:
    """What a ``poll`` runs: the site, how it is shown, the services beside it."""

    site: Site
    title: str
    fmt: str = "table"  # table | json | csv | influx
    once: bool = False
    output: Path | None = None  # -o FILE: records there (the table stays on a terminal)
    services: Sequence[Service] = ()  # the command's own: --verify-blocks, gateway, MQTT
    gateway: GatewayService | None = None
    metrics: str | None = None  # --metrics (else the site file's metrics:)
    http: HttpSettings | None = None
    log_format: str | None = None
    reload: Callable[[], Site] | None = None  # SIGHUP: the site file again
    gateway_id: str | None = None  # the id MQTT publishes under (the dashboard's)


@dataclass
class Outcome:
    """How a run ended: ``failed`` of ``total`` devices gave no reading (``--once``)."""

    failed: int = 0
    total: int = 0
    lines: list[str] = field(default_factory=list)


def run(job: PollRun, *, stop: Callable[[], asyncio.Event],
        say: Callable[[str], None]) -> Outcome:
    """Poll until ``stop()``'s event is set (once: one cycle of every device). ``say``:
    one line for the person running it (stderr)."""
    from rtupoll.app.services import poll_services
    from rtupoll.jobs.scheduler import Scheduler

    site = job.site
    scheduler = Scheduler(site)
    _adapter_warnings(site, say)
    show_table = _table_shown(job.fmt, job.output)
    console: Console | None = None
    if show_table:  # rich only for the table (records alone: less memory, faster start)
        from rich.console import Console

        console = Console(stderr=job.fmt != "table" and job.output is None)
    with _records(job.fmt, job.output, site, say) as writer:
        services = poll_services(
            site, writer, job.services, gateway=job.gateway, once=job.once,
            table=show_table, metrics=job.metrics or site.metrics or None,
            log_format=job.log_format, reload=job.reload, http=job.http, title=job.title,
            gateway_id=job.gateway_id, say=say)
        view: PollView | None = None
        if console is not None:
            from rtupoll.ui.live import PollView

            view = PollView(scheduler.buses, title=job.title, live=not job.once,
                            footers=[s.footer for s in services])
        if not job.once:
            aio.run(_forever(scheduler, writer, view, console, services, stop))
            return Outcome()
        readings = aio.run(_once(scheduler, writer, services, stop))
        if view is not None and console is not None:
            console.print(view.render(width=console.width))
        _echo_found(scheduler, say)
        return failures(site, readings)
    return Outcome()  # the records' reader left (a broken pipe, ``| head``): done


def record_format(fmt: str, site: Site, *, header: bool = True) -> RecordFormat:
    """The ``--format`` of the records (json, csv, influx); ``header``: CSV's is due."""
    from rtupoll.ui.records import CsvFormat, JsonFormat

    if fmt == "csv":
        return CsvFormat(header=header)
    if fmt == "influx":
        from rtupoll.outputs.influx import InfluxFormat

        return InfluxFormat(site)
    return JsonFormat()


@contextlib.contextmanager
def _records(fmt: str, output: Path | None, site: Site, say: Callable[[str], None]
             ) -> Iterator[RecordWriter | None]:
    """The records' writer (None: the table only), to stdout or ``output``; ``say``: what
    a reader of stdout did not take in the end."""
    if fmt == "table":
        yield None
        return
    if output is None:
        pipe = PipeWriter(sys.stdout) if threaded(sys.stdout) else None
        try:
            yield RecordWriter(pipe or sys.stdout, record_format(fmt, site))
        except BrokenPipeError:  # `rtupoll poll --format json | head`: the reader is done
            with contextlib.suppress(OSError):
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        finally:
            left = pipe.close() if pipe is not None else 0
            if left:
                say(unread(left, "bytes of records"))
        return
    try:  # whole records or nothing (rtupoll.ui.outfile)
        fh = OutputFile(output)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from None
    try:
        yield RecordWriter(fh, record_format(fmt, site, header=fh.fresh), path=output)
    finally:
        fh.close()


def _table_shown(fmt: str, output: Path | None) -> bool:
    """The live table is drawn for ``--format table``, and beside ``-o FILE`` when stdout
    is a terminal (rich's test; asked only when it could say yes, so records alone never
    import rich)."""
    if fmt == "table":
        return True
    if output is None:
        return False
    if not sys.stdout.isatty() and not any(
            os.environ.get(k) for k in ("FORCE_TERMINAL", "TTY_COMPATIBLE", "FORCE_COLOR")):
        return False
    from rich.console import Console

    return bool(Console().is_terminal)


def _adapter_warnings(site: Site, say: Callable[[str], None]) -> None:
    """One line per USB adapter whose latency timer adds more than 1 ms to every reply."""
    from rtupoll.io.latency import latency_timer, latency_warning

    for bus in site.buses:
        warning = latency_warning(bus.port, latency_timer(bus.port))
        if warning:
            say(warning)


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
                services: Sequence[Service], stop: Callable[[], asyncio.Event]
                ) -> list[Reading]:
    """One cycle of every device; records in site order once all are in."""
    got: dict[str, list[Reading]] = {}

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        got[dev.config.name] = readings
        for s in services:
            s.on_readings(dev, readings)

    from rtupoll.jobs.race import first_of

    stopped = stop()
    async with _started(scheduler, services):  # the scan, unless a signal comes first
        if await first_of(scheduler.scan_once(sink), stopped.wait()) != 0:
            raise KeyboardInterrupt
    readings = [r for d in scheduler.pollers() for r in got.get(d.config.name, [])]
    if writer is not None:  # one device at a time, with its state (influx's ``state``)
        for d in scheduler.pollers():
            if got.get(d.config.name):
                held = writer.write(got[d.config.name], d.stats.state.value)
                if held is not None:  # a reader that lags (ui.pipe_writer)
                    await held.wait()
    return readings


async def _forever(scheduler: Scheduler, writer: RecordWriter | None, view: PollView | None,
                   console: Console | None, services: Sequence[Service],
                   stop: Callable[[], asyncio.Event]) -> None:
    stopped = stop()

    def sink(dev: DevicePoller, readings: list[Reading]) -> asyncio.Event | None:
        for s in services:
            s.on_readings(dev, readings)
        if writer is None:
            return None
        try:
            return writer.write(readings, dev.stats.state.value)
        except BrokenPipeError:
            stopped.set()
            raise

    async with _started(scheduler, services):
        if view is None:
            await scheduler.run(sink, stopped)
            return
        from rich.live import Live

        with Live(view, console=console, auto_refresh=False, transient=False,
                  redirect_stdout=False, redirect_stderr=False) as live:
            painter = asyncio.create_task(_paint(live, stopped))
            try:
                await scheduler.run(sink, stopped)
            finally:
                painter.cancel()


async def _paint(live: Live, stop: asyncio.Event) -> None:
    """Redraws the table every REFRESH seconds; ``Live`` draws the first frame as it
    starts and the last as it stops (a frame costs tens of ms: not drawn twice)."""
    while True:
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(stop.wait(), REFRESH)
        if stop.is_set():
            return
        live.refresh()


def _echo_found(scheduler: Scheduler, say: Callable[[str], None]) -> None:
    """``--once``: one line per bus whose adapter's echo was found (and consumed)."""
    from rtupoll.rtu.line import ECHO_FOUND

    for bp in scheduler.buses:
        if bp.transport.echo_found:
            say(f"{bp.config.name}: {ECHO_FOUND}")


def failures(site: Site, readings: Sequence[Reading]) -> Outcome:
    """``--once``: the devices that failed, a line each (and one per silent line)."""
    failed: dict[str, Reading] = {}
    counts: dict[str, int] = {}
    for r in readings:
        if not r.ok and r.status != "absent":  # a field its variant lacks is no failure
            counts[r.device.name] = counts.get(r.device.name, 0) + 1
            if r.device.name not in failed or failed[r.device.name].status == "skipped":
                failed[r.device.name] = r
    lines = []
    for name, r in failed.items():
        d = r.device
        where = f"{name}" + (f" ({d.spec})" if name != d.spec else "")
        lines.append(f"{where}: {r.status}: {r.error} "
                     f"({counts[name]} of {len(d.fields)} fields not read)")
    for bus in site.buses:  # a silent line: most often the wrong speed
        if bus.devices and not bus.port.startswith("tcp://") and all(
                d.name in failed and failed[d.name].status == "timeout" for d in bus.devices):
            lines.append(f"nothing answered on {bus.name} at {bus.serial_text}; if the "
                         f"devices run at another speed, find it with 'rtupoll scan -p "
                         f"{bus.port}' or give --baudrate")
    return Outcome(len(failed), sum(len(b.devices) for b in site.buses), lines)
