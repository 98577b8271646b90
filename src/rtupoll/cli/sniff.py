"""``rtupoll sniff``: listen to a bus another master owns, decode what it sees.

Never sends a byte. The command wires the tap (``sniff.port``) or a capture file
(``sniff.capfile``) to a session (``sniff.session``: the sans-IO stream splitter, then
the per-device view) and prints transactions, records or the live table.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

import click

from rtupoll.cli import noted_signals
from rtupoll.cli.options import profiles_option
from rtupoll.cli.params import DEVICE, DeviceSpec
from rtupoll.config.library import load_library, load_one
from rtupoll.errors import UsageError
from rtupoll.rtu.stream import TIMEOUT, Transaction
from rtupoll.rtu.timing import Framing
from rtupoll.sniff.capfile import Capture, CaptureWriter, describe_framing, read_capture
from rtupoll.sniff.lines import frame_line
from rtupoll.sniff.model import BusView, Known
from rtupoll.sniff.session import Session, Sink
from rtupoll.ui.pipe_writer import MOST, PipeWriter, threaded, unread
from rtupoll.ui.records import to_json

REFRESH = 0.25  # seconds between redraws of the live table

EPILOG = """\b
Examples:
  rtupoll sniff -p /dev/ttyUSB0 -b 9600 huiwen-aq@3 radar-level@4
  rtupoll sniff -c site.yaml --format json --capture line1.pcapng
  rtupoll sniff --read line1.pcapng --format frames
\b
Listen-only: nothing is ever written to the port, and it is opened with DTR and
RTS low; keep the adapter's transmitter off (docs/sniff.md).
"""


@click.command(epilog=EPILOG)
@click.argument("devices", nargs=-1, type=DEVICE, metavar="[PROFILE@ADDRESS]...")
@click.option("--port", "-p", envvar="RTUPOLL_PORT", metavar="PORT",
              help="The serial port on the pair (an RS-485 adapter). Also $RTUPOLL_PORT.")
@click.option("--config", "-c", type=click.Path(dir_okay=False, path_type=Path),
              help="Site file: its devices are decoded through their profiles, its port and "
                   "serial settings are used.")
@click.option("--bus", "bus_name", default=None, metavar="NAME",
              help="The site file's bus to listen to (default: the first).")
@click.option("--baudrate", "-b", type=click.IntRange(300, 4_000_000), default=None,
              help="Baud rate (default: the site's, the capture's or the devices' profiles').")
@click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False),
              default=None, help="Parity (default N, or the site's).")
@click.option("--stopbits", type=click.Choice(["1", "2"]), default=None,
              help="Stop bits (default 1, or the site's).")
@click.option("--format", "fmt", type=click.Choice(["table", "frames", "json"]), default=None,
              help="table: live view (default on a terminal); frames: one line per "
                   "transaction (default otherwise); json: one record per decoded field, "
                   "the keys of 'poll --format json'.")
@click.option("--capture", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write every byte with its arrival time to this pcapng file.")
@click.option("--read", "read_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="Decode a capture file instead of listening.")
@click.option("--timeout", type=click.FloatRange(0.01, 60), default=TIMEOUT,
              show_default=True, metavar="SECONDS",
              help="A request with no reply for this long counts as timed out.")
@click.option("--duration", type=click.FloatRange(0, None), default=None, metavar="SECONDS",
              help="Stop after this long (default: until Ctrl-C).")
@profiles_option
def sniff(devices: tuple[DeviceSpec, ...], port: str | None, config: Path | None,
          bus_name: str | None, baudrate: int | None, parity: str | None,
          stopbits: str | None, fmt: str | None, capture: Path | None, read_path: Path | None,
          timeout: float, duration: float | None, profile_dirs: tuple[Path, ...]) -> None:
    """Listen to a bus another master owns, and decode what it sees.

    Frames are split by the 3.5-character silence and by CRC, each request is paired
    with its reply, and devices named as PROFILE@ADDRESS (or in the site file) are
    decoded through their profiles; other units are shown raw, with a "looks like"
    hint when their answers fit a bundled profile's identify rules.
    """
    if read_path is not None:
        source = click.get_current_context().get_parameter_source("port")
        if capture or (port and source is not click.core.ParameterSource.ENVIRONMENT):
            raise UsageError("--read decodes a capture file: leave out --port and --capture")
        port = None  # $RTUPOLL_PORT names the live port; a capture needs none
    known, site_framing, site_port = _known(devices, config, bus_name, profile_dirs)
    port = port or site_port
    recorded: Capture | None = read_capture(read_path) if read_path is not None else None
    if recorded is not None and recorded.stopped:  # as Wireshark: up to the damage
        click.echo(f"rtupoll: {read_path}: {recorded.stopped}", err=True)
    if recorded is None and not port:
        raise UsageError("give --port (the adapter on the pair), -c SITE, or --read FILE")
    framing = _framing(baudrate, parity, stopbits, site_framing,
                       recorded.framing if recorded else None, known)
    if fmt is None:
        fmt = "table" if sys.stdout.isatty() else "frames"
    library = list(load_library(profile_dirs).profiles.values())
    view = BusView(known, library)
    title = f"{read_path or port} {describe_framing(framing)}"

    # listening, to a pipe: written by a thread, so a reader that stalls stops neither
    # the listening nor Ctrl-C; past MOST bytes waiting, transactions are counted, not kept
    pipe = PipeWriter(sys.stdout) if (recorded is None and fmt != "table"
                                       and threaded(sys.stdout)) else None
    out: TextIO | PipeWriter = pipe or sys.stdout
    lost = [0]

    def sink(tx: Transaction, records: list[dict[str, Any]]) -> None:
        # whole lines, flushed once per chunk read (not per record): cheap at full speed
        if pipe is not None and pipe.held >= MOST:
            lost[0] += 1
            return
        if fmt == "json":
            for rec in records:
                out.write(to_json(rec) + "\n")
        elif fmt == "frames":
            out.write(frame_line(tx, view, records) + "\n")

    if recorded is not None:
        session = Session(framing, view, sink, timeout=timeout)
        try:
            session.run((data, t) for t, data in recorded.chunks)
            session.close()
            out.flush()
        except BrokenPipeError:  # `rtupoll sniff --read ... | head`: the reader is done
            return  # (cli's guard has pointed fd 1 at /dev/null; click would exit 1)
        if fmt == "table":
            from rich.console import Console

            from rtupoll.sniff.render import render

            Console().print(render(view, view.last, title))
        return
    assert port is not None
    try:
        _listen(port, framing, view, sink, fmt=fmt, title=title, timeout=timeout,
                capture=capture, duration=duration)
    finally:
        left = pipe.close() if pipe is not None else 0
        if lost[0]:
            click.echo(f"rtupoll: stdout: {lost[0]} transactions not written: "
                       f"{MOST >> 20} MiB waited for a reader", err=True)
        if left:
            click.echo(f"rtupoll: {unread(left)}", err=True)


def _listen(port: str, framing: Framing, view: BusView, sink: Sink, *, fmt: str, title: str,
            timeout: float, capture: Path | None, duration: float | None) -> None:
    from rtupoll.sniff.port import ListenPort

    tap = ListenPort(port, framing)
    writer = CaptureWriter(capture, framing, port, say=lambda m: click.echo(
        f"rtupoll: {m}", err=True)) if capture is not None else None
    session = Session(framing, view, sink, timeout=timeout, capture=writer)
    try:
        # (the handlers before the "listening" line: whoever reads it may stop us at once)
        with noted_signals() as stop:
            started = time.monotonic()
            if fmt != "table":
                click.echo(f"rtupoll sniff: listening on {port} at "
                           f"{describe_framing(framing)}, sending nothing"
                           + (f"; capturing to {capture}" if capture else ""), err=True)

            def done() -> bool:
                return bool(stop) or (duration is not None
                                      and time.monotonic() - started >= duration)

            try:
                if fmt == "table":
                    _live(tap.chunks(done), session, view, title)
                else:
                    for data, t in tap.chunks(done):
                        session.feed(data, t)
                        sys.stdout.flush()
            finally:  # (the port hung up too: what was heard until then still counts)
                session.close()
            sys.stdout.flush()
    except BrokenPipeError:  # `rtupoll sniff ... | head`: the reader is done
        pass  # (cli's guard has pointed fd 1 at /dev/null; click would exit 1)
    finally:
        if writer is not None:
            writer.close()
        tap.close()


def _live(chunks: Iterator[tuple[bytes, float]], session: Session, view: BusView,
          title: str) -> None:
    from rich.console import Console
    from rich.live import Live

    from rtupoll.sniff.render import render

    painted = 0.0
    with Live(render(view, time.time(), title), console=Console(), auto_refresh=False) as live:
        for data, t in chunks:
            session.feed(data, t)
            if t - painted >= REFRESH:
                live.update(render(view, t, title), refresh=True)
                painted = t
        live.update(render(view, time.time(), title))  # (drawn as Live stops)


def _known(devices: tuple[DeviceSpec, ...], config: Path | None, bus_name: str | None,
           profile_dirs: tuple[Path, ...]) -> tuple[list[Known], Framing | None, str | None]:
    """The devices to decode through profiles, and the site's bus (framing, port)."""
    known: list[Known] = []
    framing, port = None, None
    if config is not None:
        from rtupoll.config.site import load_site

        site = load_site(config, profile_dirs)
        buses = [b for b in site.buses if bus_name in (None, b.name)]
        if not buses:
            raise UsageError(f"{config} has no bus {bus_name!r} (buses: "
                             + ", ".join(b.name for b in site.buses) + ")")
        bus = buses[0]
        framing, port = bus.framing, bus.port
        known += [Known(d.name, d.profile, d.address) for d in bus.devices]
    elif bus_name is not None:
        raise UsageError("--bus names a bus of the site file: add -c SITE")
    for d in devices:
        p = load_one(d.profile, profile_dirs)
        known = [k for k in known if k.address != d.address]
        known.append(Known(f"{p.id}@{d.address}", p, d.address))
    return known, framing, port


def _framing(baudrate: int | None, parity: str | None, stopbits: str | None,
             site: Framing | None, recorded: Framing | None, known: list[Known]) -> Framing:
    base = recorded or site  # a capture says how it was recorded
    if base is None:
        rates = {k.profile.serial.baudrate for k in known}
        if baudrate is None and len(rates) != 1:
            raise UsageError("give --baudrate: " + ("the devices' profiles disagree"
                                                   if rates else "no device or capture says"))
        base = Framing(baudrate or rates.pop())
    return Framing(baudrate or base.baudrate, base.bytesize,
                   (parity or base.parity).upper(), float(stopbits) if stopbits
                   else base.stopbits)
