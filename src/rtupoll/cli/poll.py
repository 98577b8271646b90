"""``rtupoll poll``: watch devices on one or more buses, live, or stream their readings.

The command turns its options into a run (``rtupoll.app.poll.PollRun``: the site, from
``--config``, ad-hoc devices or the simulator, and the services the options name) and
the run's outcome into an exit status; the run itself is ``rtupoll.app.poll``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from rtupoll.app.poll import Outcome, PollRun, run
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
from rtupoll.web.options import http_options, pop_http

if TYPE_CHECKING:
    from rtupoll.config.gateway_settings import ServeConfig
    from rtupoll.gateway.service import GatewayService
    from rtupoll.jobs.services import Service

SIM_BAUDRATE = 115200  # framing assumed on a simulated line that answers at any speed


@dataclasses.dataclass(frozen=True)
class Wanted:
    """The devices the options name and how to read them (``--config``, or ``--port``
    and DEVICEs with the serial and timing options, or ``--simulate``)."""

    devices: tuple[DeviceSpec, ...]
    config: Path | None
    port: str | None
    baudrate: int | None
    parity: str | None
    stopbits: str | None
    interval: float | None
    fields: str | None
    timeout: float | None
    retries: int | None
    timeout_ceiling: float | None
    profile_dirs: tuple[Path, ...]


@dataclasses.dataclass(frozen=True)
class Target:
    """The site to poll, its title, how SIGHUP reloads it, and a line to say after."""

    site: Site
    title: str
    reload: Callable[[], Site] | None = None
    hint: str = ""


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
    http = pop_http(serve)  # --http: the dashboard (rtupoll.web)
    services = _learning(config, verify_blocks, remember_holes)  # beside the scheduler
    served = from_options(serve)  # --serve: a Modbus TCP gateway (rtupoll.gateway)
    if output is not None and fmt == "table":
        raise UsageError("--output writes json or csv: add --format json or --format csv")
    if (baud or faults) and not simulate:
        raise UsageError("--baud and --fault are for --simulate (a real bus: --baudrate)")
    if simulate and port and click.get_current_context().get_parameter_source("port") \
            is click.core.ParameterSource.ENVIRONMENT:
        port = None  # $RTUPOLL_PORT names the real bus; --simulate makes its own
    wanted = Wanted(devices, config, port, baudrate, parity, stopbits, interval, fields,
                    timeout, retries, timeout_ceiling, profile_dirs)
    with (_simulated(wanted, baud, faults) if simulate else
          contextlib.nullcontext(_given(wanted, served))) as target:
        fmt = _piped(fmt, once=once, gone=mqtt_remove_discovery)
        site, gateway = _gateway(target.site, served, services, fmt)
        mqtt_id = _mqtt(site, mqtt, mqtt_allow_writes, mqtt_remove_discovery, once,
                        services, fmt, mqtt_id)
        if mqtt_remove_discovery:
            return
        outcome = run(PollRun(site, target.title, fmt, once, output, services, gateway,
                              metrics, http, log_format, target.reload, mqtt_id),
                      stop=stop_event, say=_say)
    _ended(outcome, target.hint if fmt == "table" and not once else "")


def _say(text: str) -> None:
    click.echo(f"rtupoll: {text}", err=True)


def _ended(outcome: Outcome, hint: str) -> None:
    """The end of a run: its lines, then exit 9 if a device failed (``--once``), else a
    hint (after the simulator's demonstration)."""
    for line in outcome.lines:
        _say(line)
    if outcome.failed:
        raise ScanIncomplete(f"{outcome.failed} of {outcome.total} devices failed")
    if hint:
        click.echo(hint, err=True)


def _given(w: Wanted, served: ServeConfig | None) -> Target:
    """The site of ``--config`` or of ``--port`` and DEVICEs (a bus alone: a gateway)."""
    if w.config is not None:
        if w.devices or w.port:
            raise UsageError("give either --config or --port with devices, not both")
        if any(v is not None for v in (w.interval, w.fields, w.timeout, w.retries, w.baudrate,
                                       w.parity, w.stopbits, w.timeout_ceiling)):
            raise UsageError("--interval, --fields, --timeout, --timeout-ceiling, --retries "
                             "and serial options are set per bus and device in the site file")
        if served is not None:
            raise UsageError("with --config, set serve: per bus in the site file")
        if given_line_options() != LineOptions():
            raise UsageError("with --config, set echo:, rs485: and idle_gap: per bus in the "
                             "site file")
        config, dirs = w.config, w.profile_dirs
        return Target(load_site(config, dirs), config.name, lambda: load_site(config, dirs))
    port, devices = w.port, w.devices
    if not port and devices:
        from rtupoll.io.port_errors import example_port

        raise UsageError(f"which port is {devices[0].profile}@{devices[0].address} on? "
                         f"give --port PORT (or $RTUPOLL_PORT), e.g. -p {example_port()}, "
                         "or --simulate to try it without hardware")
    if not port:
        raise UsageError("nothing to poll: give --config FILE, or --port PORT and DEVICEs "
                         "(PROFILE@ADDRESS), or --simulate to try it without hardware")
    if not devices and served is not None:  # a pure gateway
        site = Site((BusConfig(port, port, w.baudrate or 9600, (w.parity or "N").upper(),
                               stopbits=int(w.stopbits or 1)),))
    elif not devices:
        raise UsageError(f"name the devices on {port}: PROFILE@ADDRESS... "
                         "(e.g. net-irnet-pro@1), or --serve HOST:PORT to be a gateway")
    else:
        site = from_specs(port, [(d.profile, d.address) for d in devices],
                          baudrate=w.baudrate, parity=w.parity,
                          stopbits=int(w.stopbits) if w.stopbits else None,
                          interval=DEFAULT_INTERVAL if w.interval is None else w.interval,
                          fields=_split(w.fields), timeout=w.timeout, retries=w.retries,
                          profile_dirs=w.profile_dirs, timeout_ceiling=w.timeout_ceiling)
    return Target(_with_line_options(site), port)


@contextlib.contextmanager
def _simulated(w: Wanted, baud: int | None, faults: Sequence[str]) -> Iterator[Target]:
    """``--simulate``: the simulator in-process, the devices on lines that could exist
    (the seed devices by default: four at 9600 and the CO2Meter board at 115200), one
    port each; with devices named and a baud rate, one line at that rate, as asked.
    Where there are no pseudo-terminals (Windows) each line is served over TCP on
    loopback. ``--fields`` that only other lines' devices have leave a line out."""
    if w.config or w.port:
        raise UsageError("--simulate makes its own bus: leave out --config and --port")
    from rtupoll.sim.runner import simulated_lines
    from rtupoll.sim.server import PTYS

    baudrate = baud or w.baudrate
    # --echo: the simulated adapter echoes, and the master expects it
    with simulated_lines([f"{d.profile}@{d.address}" for d in w.devices], baudrate=baudrate,
                         one_line=bool(w.devices and baudrate), faults=tuple(faults),
                         echo=given_line_options().echo, tcp=not PTYS) as running:
        lines = list(running)
        buses = []
        wanted = _split(w.fields)
        every = {n for line in lines for d in line.config.devices for n in d.profile.names()}
        for i, line in enumerate(lines):
            specs = [(d.profile.id, d.address) for d in line.config.devices]
            here = {n for d in line.config.devices for n in d.profile.names()}
            mine = [f for f in wanted if f in here or f not in every]
            if wanted and not mine:
                continue  # --fields that only other lines' devices have
            one = from_specs(line.port, specs, baudrate=line.config.line_speed or SIM_BAUDRATE,
                             interval=DEFAULT_INTERVAL if w.interval is None else w.interval,
                             fields=mine, timeout=w.timeout, retries=w.retries,
                             profile_dirs=w.profile_dirs, check_serial=False,
                             timeout_ceiling=w.timeout_ceiling)
            buses += [dataclasses.replace(b, name=f"line{i + 1}" if len(lines) > 1
                                          else "simulated") for b in one.buses]
        site = _with_line_options(dataclasses.replace(one, buses=tuple(buses)))
        title = (f"simulated: {len(buses)} lines" if len(buses) > 1 else "simulated bus") + \
            f", {'wire timing' if baudrate else 'untimed'}"
        hint = ""
        if not faults:
            from rtupoll.io.port_errors import example_port

            dead = lines[0].config.devices[-1].address  # one that exists on this bus
            hint = (f"That was a simulated bus. Try --fault {dead}:dead (a dead device) or "
                    f"--baud 9600 (real wire timing).\nYour own devices: rtupoll poll -p "
                    f"{example_port()} -b BAUDRATE PROFILE@ADDRESS...")
        yield Target(site, title, hint=hint)


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
          services: list[Service], fmt: str, gateway_id: str | None = None) -> str | None:
    """``--mqtt`` or the site file's ``mqtt:``: the MQTT service (rtupoll.outputs.mqtt),
    or ``--mqtt-remove-discovery`` done (nothing is polled then). The gateway id it
    publishes under (none without MQTT): the dashboard's."""
    if site.mqtt is None and not url:
        if allow_writes or remove or gateway_id is not None:
            raise UsageError("--mqtt-allow-writes, --mqtt-id and --mqtt-remove-discovery need "
                             "--mqtt URL (or mqtt: in the site file)")
        return None
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
            from rtupoll.numbers import count

            configs = count(len(gone.configs), "Home Assistant discovery config")
            click.echo(f"rtupoll: removed {configs} ({settings.discovery_prefix}/device/...)"
                       f" and {count(len(gone.topics), 'retained topic')} under "
                       f"{settings.base} (bridge state and info, availability) from "
                       f"{settings.where}", err=True)
        return settings.gateway_id
    # under the live table its news is a footer line rather than log lines
    services.append(mqtt_out.MqttService(settings, site, once=once,
                                         log_lines=fmt != "table"))
    return settings.gateway_id


def _learning(config: Path | None, verify: bool, remember: bool) -> list[Service]:
    """``--verify-blocks`` and ``--remember-holes``: services (rtupoll.jobs.hole_services)."""
    if not verify and not remember:
        return []
    from rtupoll.jobs.hole_services import RememberHoles, VerifyBlocks
    from rtupoll.jobs.holes import HoleStore

    services: list[Service] = []
    if remember:
        if config is None:
            raise UsageError("--remember-holes keeps them next to the site file: give "
                             "--config FILE")
        services.append(RememberHoles(HoleStore.for_site(config), _say))
    if verify:
        services.append(VerifyBlocks(_say))
    return services


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
