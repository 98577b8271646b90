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
import sys
from collections.abc import AsyncIterator, Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import click

from rtupoll import aio
from rtupoll.cli import stop_event
from rtupoll.cli.options import (
    LineOptions,
    format_option,
    given_line_options,
    line_options,
    profiles_option,
    service_options,
)
from rtupoll.cli.params import DEVICE, DeviceSpec, Seconds
from rtupoll.cli.serve_options import from_options, serve_options
from rtupoll.config.site import DEFAULT_INTERVAL, BusConfig, Site, from_specs, load_site
from rtupoll.errors import ScanIncomplete, UsageError
from rtupoll.ui.outfile import OutputFile
from rtupoll.ui.records import POLL_KEYS, CsvWriter, JsonRecords, reading_record
from rtupoll.web.options import http_options, pop_http

if TYPE_CHECKING:
    from rich.console import Console
    from rich.live import Live

    from rtupoll.config.gateway_settings import ServeConfig
    from rtupoll.config.http_settings import HttpSettings
    from rtupoll.gateway.service import GatewayService
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.services import Service
    from rtupoll.jobs.stats import Reading
    from rtupoll.sim.runner import SimulatedBus
    from rtupoll.ui.live import PollView

REFRESH = 0.25  # seconds between redraws of the live table
SIM_BAUDRATE = 115200  # framing assumed on a simulated line that answers at any speed


class RecordWriter:
    """JSON lines, CSV or Influx line protocol, one whole batch per write, flushed: no
    partial lines, ever. ``path``: the file ``out`` is, reopened by ``reopen`` (SIGHUP)."""

    def __init__(self, out: TextIO | OutputFile, fmt: str, *, header: bool = True,
                 path: Path | None = None) -> None:
        self.out, self.fmt, self.path = out, fmt, path
        self._buf = io.StringIO()
        self._csv = CsvWriter(self._buf, POLL_KEYS, header=header) if fmt == "csv" else None
        self._json = JsonRecords()
        self.buses: dict[str, str] = {}  # device name -> bus name (influx's bus tag)
        self._influx = None
        if fmt == "influx":
            from rtupoll.outputs.influx import InfluxFormatter

            self._influx = InfluxFormatter(self.buses)

    def reopen(self) -> None:
        """Continue in a new file at ``path`` (logrotate moved the old one away)."""
        if self.path is None:
            return
        if isinstance(self.out, OutputFile):
            self.out.reopen()
        else:
            old, self.out = self.out, OutputFile(self.path)
            old.close()
        if self._csv is not None:
            self._csv = CsvWriter(self._buf, POLL_KEYS, header=self.out.fresh)

    def write(self, readings: Sequence[Reading], state: str = "") -> None:
        if self._influx is None and self._csv is None:
            line = self._json.line
            text = "".join([line(r) for r in readings])
        else:
            if self._influx is not None:
                self._buf.write(self._influx.format(readings, state))
            elif self._csv is not None:
                for r in readings:
                    self._csv.write(reading_record(r))
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
@line_options
@click.option("--interval", "-i", type=Seconds(0, 86_400), default=None,
              help=f"Seconds between scans of each DEVICE [default: {DEFAULT_INTERVAL:g}; "
                   "0: as fast as the bus allows].")
@click.option("--timeout", type=Seconds(0.01, 30), default=None,
              help="Pin each DEVICE's response timeout, in seconds (default: learned from "
                   "its replies, starting at its profile's).")
@click.option("--retries", type=click.IntRange(0, 10), default=None,
              help="Immediate retries per request (default: the profile's).")
@click.option("--timeout-ceiling", type=Seconds(0.05, 30), default=None,
              help="The longest timeout learned for each DEVICE [default: 3].")
@click.option("--verify-blocks", is_flag=True,
              help="First read each block of several fields also field by field; where "
                   "they disagree (a silent shift), say so and stop bridging there.")
@click.option("--remember-holes", is_flag=True,
              help="With --config: keep the holes learned per device in SITE.holes.json "
                   "next to the site file, and start from them.")
@click.option("--fields", "-f", "fields", default=None, metavar="NAME[,NAME...]",
              help="Poll only these fields (each DEVICE polls those it has).")
@click.option("--once", is_flag=True,
              help="Read every device once, print, exit (9 if any device failed).")
@format_option("table", "json", "csv", "influx")
@click.option("--output", "-o", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Append json/csv/influx records to this file (the table stays on the "
                   "terminal; SIGHUP reopens it).")
@click.option("--simulate", is_flag=True,
              help="Poll simulated devices (no DEVICE: the five seed devices, on two lines: "
                   "four at 9600 baud and the CO2Meter board at 115200).")
@click.option("--baud", type=click.IntRange(300, 4_000_000), default=None,
              help="--simulate: take the real wire time at this baud rate.")
@click.option("--fault", "faults", multiple=True, metavar="SPEC",
              help="--simulate: inject a fault, e.g. 3:dead, 4:crc@10%, slow=1@5- "
                   "(repeatable; see 'rtupoll simulate --help').")
@profiles_option
@service_options
@serve_options
@http_options()
@click.option("--mqtt", "mqtt", metavar="URL", default=None,
              help="Publish to an MQTT broker: mqtt://[USER[:PASS]@]HOST[:PORT][/BASE] "
                   "(mqtts:// for TLS; also mqtt: in the site file; docs/mqtt.md).")
@click.option("--mqtt-allow-writes", is_flag=True,
              help="Take BASE/DEVICE/set commands from the broker (checked like 'write').")
@click.option("--mqtt-remove-discovery", is_flag=True,
              help="Remove this gateway's Home Assistant discovery from the broker, and exit.")
@click.option("--mqtt-id", "mqtt_id", metavar="ID", default=None,
              help="This gateway's id on the broker (default: the host name): its base "
                   "topic rtupoll/ID and Home Assistant ids (docs/mqtt.md).")
def poll(devices: tuple[DeviceSpec, ...], config: Path | None, port: str | None,
         baudrate: int | None, parity: str | None, stopbits: str | None,
         interval: float | None, timeout: float | None, retries: int | None,
         fields: str | None, once: bool, fmt: str,
         output: Path | None, simulate: bool, baud: int | None, faults: tuple[str, ...],
         profile_dirs: tuple[Path, ...], metrics: str | None, log_format: str | None,
         mqtt: str | None, mqtt_allow_writes: bool, mqtt_remove_discovery: bool,
         timeout_ceiling: float | None = None, verify_blocks: bool = False,
         remember_holes: bool = False, mqtt_id: str | None = None, **serve: Any) -> None:
    """Poll devices and show their decoded readings live.

    \b
    rtupoll poll --simulate                      # five simulated devices on two lines
    rtupoll poll -p /dev/ttyUSB0 -b 9600 net-irnet-pro@1 huiwen-aq@3
    rtupoll poll -c site.yaml --format json -o readings.jsonl
    rtupoll poll -c site.yaml --once --format csv

    DEVICE is PROFILE@ADDRESS. Stop with Ctrl-C (or SIGTERM): the current line is
    finished, nothing is left half-written, and the exit status is 0.
    """
    services: list[Service] = []  # run beside the scheduler (rtupoll.jobs.services)
    http = pop_http(serve)  # --http: the dashboard (rtupoll.web)
    _learning(services, config, verify_blocks, remember_holes)
    served = from_options(serve)  # --serve: a Modbus TCP gateway (rtupoll.gateway)
    if output is not None and fmt == "table":
        raise UsageError("--output writes json or csv: add --format json or --format csv")
    if (baud or faults) and not simulate:
        raise UsageError("--baud and --fault are for --simulate (a real bus: --baudrate)")
    if simulate and port and click.get_current_context().get_parameter_source("port") \
            is click.core.ParameterSource.ENVIRONMENT:
        port = None  # $RTUPOLL_PORT names the real bus; --simulate makes its own
    if simulate:
        if config or port:
            raise UsageError("--simulate makes its own bus: leave out --config and --port")
        # --echo: the simulated adapter echoes, and the master expects it
        with _simulated(devices, baud or baudrate, faults,
                        echo=given_line_options().echo) as lines:
            buses = []
            wanted = _split(fields)
            every = {n for line in lines for d in line.config.devices
                     for n in d.profile.names()}
            for i, line in enumerate(lines):
                specs = [(d.profile.id, d.address) for d in line.config.devices]
                here = {n for d in line.config.devices for n in d.profile.names()}
                mine = [f for f in wanted if f in here or f not in every]
                if wanted and not mine:
                    continue  # --fields that only other lines' devices have
                speed = line.config.line_speed or SIM_BAUDRATE
                one = from_specs(line.port, specs, baudrate=speed,
                                 interval=DEFAULT_INTERVAL if interval is None else interval,
                                 fields=mine, timeout=timeout, retries=retries,
                                 profile_dirs=profile_dirs, check_serial=False,
                                 timeout_ceiling=timeout_ceiling)
                buses += [dataclasses.replace(b, name=f"line{i + 1}" if len(lines) > 1
                                              else "simulated") for b in one.buses]
            site = _with_line_options(dataclasses.replace(one, buses=tuple(buses)))
            timing = "wire timing" if baud or baudrate else "untimed"
            title = (f"simulated: {len(buses)} lines" if len(buses) > 1
                     else "simulated bus") + f", {timing}"
            fmt = _piped(fmt, once=once, gone=mqtt_remove_discovery)
            site, gateway = _gateway(site, served, services, fmt)
            if _mqtt(site, mqtt, mqtt_allow_writes, mqtt_remove_discovery, once, services,
                     fmt, mqtt_id):
                return
            _run(site, once=once, fmt=fmt, output=output, title=title, services=services,
                 metrics=metrics, log_format=log_format, http=http, gateway=gateway)
        if fmt == "table" and not once and not faults:
            dead = lines[0].config.devices[-1].address  # one that exists on this bus
            from rtupoll.io.port_errors import example_port

            click.echo(f"That was a simulated bus. Try --fault {dead}:dead (a dead device) "
                       "or --baud 9600 (real wire timing).\nYour own devices: rtupoll poll "
                       f"-p {example_port()} -b BAUDRATE PROFILE@ADDRESS...", err=True)
        return
    if config is not None:
        if devices or port:
            raise UsageError("give either --config or --port with devices, not both")
        if any(v is not None for v in (interval, fields, timeout, retries, baudrate, parity,
                                       stopbits, timeout_ceiling)):
            raise UsageError("--interval, --fields, --timeout, --timeout-ceiling, --retries "
                             "and serial options are set per bus and device in the site file")
        if served is not None:
            raise UsageError("with --config, set serve: per bus in the site file")
        if given_line_options() != LineOptions():
            raise UsageError("with --config, set echo:, rs485: and idle_gap: per bus in the "
                             "site file")
        site = load_site(config, profile_dirs)
    else:
        if not port and devices:
            from rtupoll.io.port_errors import example_port

            raise UsageError(f"which port is {devices[0].profile}@{devices[0].address} on? "
                             f"give --port PORT (or $RTUPOLL_PORT), e.g. -p {example_port()}, "
                             "or --simulate to try it without hardware")
        if not port:
            raise UsageError("nothing to poll: give --config FILE, or --port PORT and DEVICEs "
                             "(PROFILE@ADDRESS), or --simulate to try it without hardware")
        if not devices and served is not None:  # a pure gateway
            site = Site((BusConfig(port, port, baudrate or 9600, (parity or "N").upper(),
                                   stopbits=int(stopbits or 1)),))
        elif not devices:
            raise UsageError(f"name the devices on {port}: PROFILE@ADDRESS... "
                             "(e.g. net-irnet-pro@1), or --serve HOST:PORT to be a gateway")
        else:
            site = from_specs(port, [(d.profile, d.address) for d in devices],
                              baudrate=baudrate, parity=parity,
                              stopbits=int(stopbits) if stopbits else None,
                              interval=DEFAULT_INTERVAL if interval is None else interval,
                              fields=_split(fields), timeout=timeout, retries=retries,
                              profile_dirs=profile_dirs, timeout_ceiling=timeout_ceiling)
        site = _with_line_options(site)
    fmt = _piped(fmt, once=once, gone=mqtt_remove_discovery)
    site, gateway = _gateway(site, served, services, fmt)
    if _mqtt(site, mqtt, mqtt_allow_writes, mqtt_remove_discovery, once, services, fmt,
             mqtt_id):
        return
    _run(site, once=once, fmt=fmt, output=output,
         title=config.name if config else str(port), services=services,
         metrics=metrics, log_format=log_format, http=http, gateway=gateway,
         reload=(lambda: load_site(config, profile_dirs)) if config is not None else None)


def _gateway(site: Site, served: ServeConfig | None, services: list[Service], fmt: str
             ) -> tuple[Site, GatewayService | None]:
    """``--serve`` on the (one) bus, and the gateway service for every bus that serves."""
    if served is not None:
        if len(site.buses) != 1:
            raise UsageError(f"--serve serves one bus, and there are {len(site.buses)}: name "
                             "devices of one line, or use a site file with serve: per bus")
        site = dataclasses.replace(site, buses=(dataclasses.replace(site.buses[0],
                                                                    serve=served),))
    if any(b.serve for b in site.buses):
        from rtupoll.gateway.service import GatewayService, to_info, to_log

        # a live table on a terminal shows the gateway's log lines in its footer
        live = fmt == "table" and sys.stdout.isatty()
        gateway = GatewayService(log=None if live else to_log, info=None if live else to_info)
        services.append(gateway)
        return site, gateway
    return site, None


def _mqtt(site: Site, url: str | None, allow_writes: bool, remove: bool, once: bool,
          services: list[Service], fmt: str, gateway_id: str | None = None) -> bool:
    """``--mqtt`` or the site file's ``mqtt:``: the MQTT service (rtupoll.outputs.mqtt).
    True when ``--mqtt-remove-discovery`` did its job: nothing is polled then."""
    if site.mqtt is None and not url:
        if allow_writes or remove or gateway_id is not None:
            raise UsageError("--mqtt-allow-writes, --mqtt-id and --mqtt-remove-discovery need "
                             "--mqtt URL (or mqtt: in the site file)")
        return False
    from rtupoll.outputs import mqtt as mqtt_out

    settings = mqtt_out.from_options(site, url, allow_writes=allow_writes,
                                     gateway_id=gateway_id)
    assert settings is not None
    if remove:
        gone = mqtt_out.remove_discovery_now(settings, site)
        if not gone.configs and not gone.topics:
            click.echo(f"rtupoll: nothing to remove: {settings.where} holds no Home "
                       f"Assistant discovery config of gateway {settings.gateway_id!r} and "
                       f"no retained topic under {settings.base}", err=True)
        else:
            from rtupoll.figures import count

            configs = count(len(gone.configs), "Home Assistant discovery config")
            click.echo(f"rtupoll: removed {configs} ({settings.discovery_prefix}/device/...)"
                       f" and {count(len(gone.topics), 'retained topic')} under "
                       f"{settings.base} (bridge state and info, availability) from "
                       f"{settings.where}", err=True)
        return True
    # under the live table its news is a footer line rather than log lines
    services.append(mqtt_out.MqttService(settings, site, once=once,
                                         log_lines=fmt != "table"))
    return False


def _learning(services: list[Service], config: Path | None, verify: bool,
              remember: bool) -> None:
    """``--verify-blocks`` and ``--remember-holes``: services (rtupoll.jobs.hole_services)."""
    if not verify and not remember:
        return
    from rtupoll.jobs.hole_services import RememberHoles, VerifyBlocks
    from rtupoll.jobs.holes import HoleStore

    def say(text: str) -> None:
        click.echo(f"rtupoll: {text}", err=True)

    if remember:
        if config is None:
            raise UsageError("--remember-holes keeps them next to the site file: give "
                             "--config FILE")
        services.append(RememberHoles(HoleStore.for_site(config), say))
    if verify:
        services.append(VerifyBlocks(say))


def _piped(fmt: str, *, once: bool, gone: bool) -> str:
    """The live table needs a terminal: piped (``rtupoll poll | tee``), readings go out
    as JSON lines as they come, and one stderr line says so and names ``--format``."""
    if fmt != "table" or once or gone or sys.stdout.isatty():
        return fmt
    click.echo("rtupoll: stdout is not a terminal: readings go out as JSON lines as they "
               "come (--format json; or csv, influx; --once for one table)", err=True)
    return "json"


def _split(fields: str | None) -> list[str]:
    return [f.strip() for f in (fields or "").split(",") if f.strip()]


def _with_line_options(site: Site) -> Site:
    """--echo, --rs485 and --idle-gap on every bus of a site made from the command line."""
    given = given_line_options()
    return dataclasses.replace(site, buses=tuple(
        dataclasses.replace(b, echo=given.echo, rs485=given.rs485, idle_gap=given.idle_gap)
        for b in site.buses))


@contextlib.contextmanager
def _simulated(devices: Sequence[DeviceSpec], baudrate: int | None, faults: Sequence[str],
               *, echo: bool = False) -> Iterator[list[SimulatedBus]]:
    """Start the simulator in-process: the devices on lines that could exist (the seed
    devices by default: four at 9600 and the CO2Meter board at 115200), one port each.
    With devices named and a baud rate, they are one line at that rate, as asked. Where
    there are no pseudo-terminals (Windows) each line is served over TCP on loopback."""
    from rtupoll.sim.runner import simulated_lines
    from rtupoll.sim.server import PTYS

    with simulated_lines([f"{d.profile}@{d.address}" for d in devices], baudrate=baudrate,
                         one_line=bool(devices and baudrate), faults=tuple(faults),
                         echo=echo, tcp=not PTYS) as lines:
        yield list(lines)


def _run(site: Site, *, once: bool, fmt: str, output: Path | None, title: str,
         services: Sequence[Service] = (), metrics: str | None = None,
         log_format: str | None = None, reload: Callable[[], Site] | None = None,
         http: HttpSettings | None = None, gateway: GatewayService | None = None) -> None:
    from rtupoll.app.services import poll_services
    from rtupoll.jobs.scheduler import Scheduler

    scheduler = Scheduler(site)
    _adapter_warnings(site)
    show_table = _table_shown(fmt, output)
    console: Console | None = None
    if show_table:  # rich only for the table (records alone: less memory, faster start)
        from rich.console import Console

        console = Console(stderr=fmt != "table" and output is None)
    with _sink(fmt, output) as writer:
        services = poll_services(
            site, writer, services, gateway=gateway, once=once, table=show_table,
            metrics=metrics or site.metrics or None, log_format=log_format, reload=reload,
            http=http, title=title, say=lambda t: click.echo(f"rtupoll: {t}", err=True))
        view: PollView | None = None
        if console is not None:
            from rtupoll.ui.live import PollView

            view = PollView(scheduler.buses, title=title, live=not once,
                            footers=[s.footer for s in services])
        if once:
            readings = aio.run(_once(scheduler, writer, services))
            if view is not None and console is not None:
                console.print(view.render(width=console.width))
            _echo_found(scheduler)
            _report_failures(site, readings)
        else:
            aio.run(_forever(scheduler, writer, view, console, services))


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


def _adapter_warnings(site: Site) -> None:
    """One line per USB adapter whose latency timer adds more than 1 ms to every reply."""
    from rtupoll.io.latency import latency_timer, latency_warning

    for bus in site.buses:
        warning = latency_warning(bus.port, latency_timer(bus.port))
        if warning:
            click.echo(f"rtupoll: {warning}", err=True)


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
    try:  # whole records or nothing (rtupoll.ui.outfile)
        fh = OutputFile(output)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from None
    try:
        yield RecordWriter(fh, fmt, header=fh.fresh, path=output)
    finally:
        fh.close()


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

    from rtupoll.jobs.race import first_of

    stop = stop_event()
    async with _started(scheduler, services):  # the scan, unless a signal comes first
        if await first_of(scheduler.scan_once(sink), stop.wait()) != 0:
            raise KeyboardInterrupt
    readings = [r for d in scheduler.pollers() for r in got.get(d.config.name, [])]
    if writer is not None:  # one device at a time, with its state (influx's ``state``)
        for d in scheduler.pollers():
            if got.get(d.config.name):
                writer.write(got[d.config.name], d.stats.state.value)
    return readings


async def _forever(scheduler: Scheduler, writer: RecordWriter | None, view: PollView | None,
                   console: Console | None, services: Sequence[Service]) -> None:
    stop = stop_event()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        for s in services:
            s.on_readings(dev, readings)
        if writer is None:
            return
        try:
            writer.write(readings, dev.stats.state.value)
        except BrokenPipeError:
            stop.set()
            raise

    async with _started(scheduler, services):
        if view is None:
            await scheduler.run(sink, stop)
            return
        from rich.live import Live

        with Live(view, console=console, auto_refresh=False, transient=False,
                  redirect_stdout=False, redirect_stderr=False) as live:
            painter = asyncio.create_task(_paint(live, stop))
            try:
                await scheduler.run(sink, stop)
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


def _echo_found(scheduler: Scheduler) -> None:
    """``--once``: one stderr line per bus whose adapter's echo was found (and consumed)."""
    from rtupoll.rtu.line import ECHO_FOUND

    for bp in scheduler.buses:
        if getattr(bp.transport, "echo_found", False):
            click.echo(f"rtupoll: {bp.config.name}: {ECHO_FOUND}", err=True)


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
    for bus in site.buses:  # a silent line: most often the wrong speed
        if bus.devices and not bus.port.startswith("tcp://") and all(
                d.name in failed and failed[d.name].status == "timeout" for d in bus.devices):
            click.echo(f"rtupoll: nothing answered on {bus.name} at {bus.serial_text}; if "
                       f"the devices run at another speed, find it with 'rtupoll scan -p "
                       f"{bus.port}' or give --baudrate", err=True)
    if failed:
        total = sum(len(b.devices) for b in site.buses)
        raise ScanIncomplete(f"{len(failed)} of {total} devices failed")
