"""``rtupoll simulate``: serve simulated devices on a pseudo-terminal or RTU-over-TCP.

The first thing a newcomer without hardware runs, so its output says what is being
served, where, and what to try next; it runs until Ctrl-C or SIGTERM and exits 0.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import click

from rtupoll.cli import noted_signals
from rtupoll.cli.options import profiles_option
from rtupoll.cli.params import Seconds
from rtupoll.errors import UsageError
from rtupoll.rtu import Table
from rtupoll.ui.pipe_writer import MOST, PipeWriter, threaded, unread

if TYPE_CHECKING:
    from rtupoll.sim.runner import SimulatedBus, SimulatedLines
    from rtupoll.sim.server import WireFrame

FAULT_HELP = (
    "Inject a fault (repeatable): [ADDRESS:]KIND[=ARG][@WHEN]. KIND: dead, slow[=SECONDS], "
    "crc, stray[=BYTE], truncate[=N], wrong-id[=ID], wrong-id-first[=ID], "
    "exception[=CODE], lose-first[=N]. WHEN: a rate (0.1 or 10%) or request numbers "
    "(3 | 2,4 | 5-7 | 10-). No ADDRESS: the whole bus. E.g. 3:dead, slow=1.5@2, crc@10%.")


@click.command()
@click.argument("devices", nargs=-1, metavar="[PROFILE@ADDRESS]...")
@click.option("--baud", type=click.IntRange(300, 4_000_000), default=None,
              help="Wire timing: requests and replies take their real time at this baud "
                   "rate (8N1), plus the 3.5-character silence and each device's turnaround. "
                   "Default: no timing, replies at once.")
@click.option("--turnaround", type=Seconds(0, 10), default=None, metavar="SECONDS",
              help="Every device's time from request to reply (default: each profile's "
                   "limits.turnaround, applied with --baud).")
@click.option("--scenario", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Scenario YAML: devices, pinned values, options, faults (docs/simulator.md).")
@click.option("--set", "sets", multiple=True, metavar="PROFILE@ADDR.FIELD=VALUE",
              help="Pin a field's value (repeatable), e.g. huiwen-aq@3.co2=800, "
                   "net-irnet-pro@1.warning=WARMUP_WARNING.")
@click.option("--option", "options", multiple=True, metavar="PROFILE@ADDR.NAME=VALUE",
              help="A device option (repeatable): variant=N, write_reply=echo|short|none, "
                   "turnaround=SECONDS.")
@click.option("--fault", "faults", multiple=True, metavar="SPEC", help=FAULT_HELP)
@click.option("--seed", type=int, default=None,
              help="Seed for moving values and fault rates (default 0): same seed, same run.")
@click.option("--tick", type=Seconds(0, 3600), default=1.0, show_default=True,
              metavar="SECONDS", help="How often values move; 0 freezes them.")
@click.option("--link", type=click.Path(dir_okay=False), default=None,
              help="Also make this symbolic link to the pty (a stable port name).")
@click.option("--tcp", default=None, metavar="HOST:PORT",
              help="Serve RTU frames over TCP (like a serial gateway) instead of a pty.")
@click.option("--tap", type=click.Path(dir_okay=False), default=None,
              help="Also offer a second pty, linked here, that receives a copy of every byte "
                   "on the line (for 'rtupoll sniff').")
@click.option("--replay", type=click.Path(dir_okay=False, exists=True, path_type=Path),
              default=None, help="Serve the devices of a capture ('rtupoll sniff --capture'): "
                                 "their captured replies, values and reply times.")
@click.option("--verbose", "-v", is_flag=True, help="Print every frame on the wire.")
@click.option("--echo", is_flag=True,
              help="Behave like an adapter that echoes: every byte the master sends comes "
                   "back to it before the reply, with --baud byte by byte as it leaves the "
                   "wire (a master needs --echo).")
@profiles_option
def simulate(devices: tuple[str, ...], baud: int | None, turnaround: float | None,
             scenario: Path | None, sets: tuple[str, ...], options: tuple[str, ...],
             faults: tuple[str, ...], seed: int | None, tick: float, link: str | None,
             tcp: str | None, tap: str | None, replay: Path | None, verbose: bool,
             echo: bool, profile_dirs: tuple[Path, ...]) -> None:
    """Serve simulated Modbus RTU devices until interrupted.

    Devices are PROFILE@ADDRESS (e.g. net-irnet-pro@1 huiwen-aq@3); with none, one of
    each bundled profile. Devices go on lines that could exist, one pty each: a line
    runs at one speed, so devices that share no speed get a line each (the default
    demo: four devices at 9600, the CO2Meter board at 115200). A line answers only
    clients that opened it at its speed. With --baud N every named device is on one
    line at N, with real wire timing. Or connect to --tcp.
    """
    from rtupoll.sim.runner import simulated_lines
    from rtupoll.sim.server import NO_PTY, PTYS

    if tcp is None and not PTYS:  # (Windows)
        raise UsageError(NO_PTY)
    if link and tcp:
        raise UsageError("--link names a pty; it cannot be used with --tcp")
    if tcp is not None and (":" not in tcp or not tcp.rpartition(":")[2].isdigit()
                            or int(tcp.rpartition(":")[2]) > 65535):
        raise UsageError(f"--tcp {tcp!r} is not HOST:PORT, PORT 0..65535 (e.g. 127.0.0.1:5020)")
    from rtupoll.io import clock as line_clock

    t0 = line_clock.now()  # (the wire log's clock)
    if replay is not None:
        from rtupoll.sim.replay import replay_lines

        if devices or scenario or sets or options or faults:
            raise UsageError("--replay serves the capture's devices: leave out devices, "
                             "--scenario, --set, --option and --fault")
        lines = replay_lines(replay, baud=baud, tcp=tcp or False, link=link, tap=tap)
    else:
        lines = simulated_lines(
            devices, baudrate=baud, one_line=bool(baud and (devices or scenario)),
            faults=faults, scenario=scenario, tcp=tcp or False, seed=seed, sets=sets,
            options=options, turnaround=turnaround, tick=tick or None,
            profile_dirs=profile_dirs, link=link, tap=tap, echo=echo)
    for line in lines:  # (replay too)
        line.echo = echo
    shown = _Shown()
    if verbose:
        for i, line in enumerate(lines):
            line.on_wire = shown.shower(t0, f"line {i + 1} " if len(lines) > 1 else "")
    with noted_signals() as caught:
        lines.start()
        try:
            if replay is not None:
                from rtupoll.sim.replay import banner

                click.echo("\n".join(banner(lines, replay)))
            else:
                _banner(lines)
            sys.stdout.flush()  # a pipe is block-buffered; whoever reads us needs the port
            if verbose and threaded(sys.stdout):
                shown.to_pipe()
            while not caught:
                time.sleep(0.1)  # (the handler only notes a signal: seen within 0.1 s)
        finally:
            lines.stop()
    requests = replies = 0
    for line in lines:
        assert line.engine is not None
        requests += line.engine.requests
        replies += line.engine.replies
    newline = "\n" if caught[:1] == [signal.SIGINT] else ""  # after the terminal's ^C
    shown.line(f"{newline}stopped after {requests} requests ({replies} replies).")
    shown.close()


class _Shown:
    """What ``simulate`` prints once it serves: --verbose's frames (from the simulator's
    thread) and its last line. To a pipe they go through a ``PipeWriter``, so a reader
    that stalls never holds the simulated devices' replies; past ``MOST`` bytes waiting,
    or with the reader gone, frames are counted, not kept."""

    def __init__(self) -> None:
        self.pipe: PipeWriter | None = None
        self.lost = 0
        self._lock = threading.Lock()  # a frame is printed before the writer, or by it

    def to_pipe(self) -> None:
        """From now on through a ``PipeWriter`` (which first flushes what was printed)."""
        with self._lock:
            self.pipe = PipeWriter(sys.stdout)

    def shower(self, t0: float, prefix: str) -> Callable[[WireFrame], None]:
        def show(frame: WireFrame) -> None:
            self.line(f"{frame.time - t0:10.4f}  {prefix}{frame}")
        return show

    def line(self, text: str) -> None:
        with self._lock:
            if self.pipe is None:
                click.echo(text)
            elif self.pipe.held >= MOST:
                self.lost += 1
            else:
                try:
                    self.pipe.write(text + "\n")
                except OSError:  # the reader has gone: the devices go on answering
                    self.lost += 1

    def close(self) -> None:
        left = self.pipe.close() if self.pipe is not None else 0
        if self.lost:
            click.echo(f"rtupoll: stdout: {self.lost} frames not written: their reader "
                       f"went away or left {MOST >> 20} MiB unread", err=True)
        if left:
            click.echo(f"rtupoll: {unread(left)}", err=True)


def _banner(lines: SimulatedLines) -> None:
    from rtupoll.sim.scenario import cannot_run

    many = len(lines) > 1
    tries: list[str] = []
    for i, bus in enumerate(lines):
        c = bus.config
        devices = bus.device_list()
        speed = c.line_speed
        if bus.port.startswith("tcp:"):
            what = "RTU over TCP, like a serial gateway" + (f", at {speed} baud" if speed
                                                             else "")
        elif speed:
            what = f"a serial port: open it at {speed} baud"
        else:
            what = "a serial port: open it at any baud rate"
        click.echo(f"Simulating {len(devices)} device{'s' if len(devices) != 1 else ''} on "
                   + click.style(bus.port, bold=True)
                   + (f", linked as {bus.link}" if bus.link else "")
                   + (f", line {i + 1}" if many else "") + f" ({what})")
        if bus.tap_port:
            click.echo(f"  tap: {bus.tap} -> {bus.tap_port} (a copy of every byte on the "
                       "line, for 'rtupoll sniff')")
        _devices(bus)
        if c.faults:
            click.echo("  bus faults: " + ", ".join(str(f) for f in c.faults))
        for note in cannot_run(c):
            click.echo(f"  note: {note}: a real one would not answer on this line")
        tries += _hints(bus, first=i == 0)
    timed = lines.lines[0].config
    if timed.baudrate:
        fr = lines.lines[0].framing
        assert fr is not None
        click.echo(f"Wire timing: {timed.baudrate} baud 8N1 (3.5-character silence "
                   f"{fr.silence * 1000:.2f} ms, plus each device's turnaround).")
    else:
        click.echo("Wire timing: off, replies at once (--baud N for real wire time).")
    click.echo(f"Values move every {timed.tick:g} s (seed {timed.seed})." if timed.tick
               else f"Values are frozen (seed {timed.seed}).")
    click.echo("Try:")
    for t in tries:
        click.echo(f"  {t}")
    click.echo("Press Ctrl-C to stop.")


def _devices(bus: SimulatedBus) -> None:
    rows = []
    for d in bus.device_list():
        p = d.profile
        any_ = p.addresses.any
        also = f" (also answers {any_} = 0x{any_:02X})" if any_ and any_ != d.address else ""
        opts = [f"{p.variant.name} {d.variant}" if p.variant else "",
                f"FC06 reply {d.write_reply}" if d.write_reply != "echo" else "",
                *(f"fault {f}" for f in d.config.faults)]
        extra = "; ".join(o for o in opts if o)
        rows.append((str(d.address), p.id, f"{p.vendor} {p.model}{also}"
                     + (f" [{extra}]" if extra else "")))
    width = max(len(r[1]) for r in rows)
    click.echo(f"  {'addr':>4}  {'profile':<{width}}  device")
    for addr, pid, what in rows:
        click.echo(f"  {addr:>4}  {pid:<{width}}  {what}")


def _hints(bus: SimulatedBus, *, first: bool) -> list[str]:
    """Commands that work as printed against this line: its port and its speed."""
    from rtupoll.sim.scenario import speeds

    c = bus.config
    speed = c.line_speed
    devices = [d for d in bus.device_list() if speed is None or speed in speeds(d.profile)]
    if not devices:
        return []
    port = bus.link or bus.port
    b = f" -b {speed}" if speed else ""
    out = []
    if first:
        d = devices[0]
        out.append(f"rtupoll read -p {port}{b} {d.profile.id}@{d.address}")
    if speed or len({d.profile.serial.baudrate for d in devices}) == 1:
        out.append(f"rtupoll poll -p {port}{b} " + " ".join(
            f"{d.profile.id}@{d.address}" for d in devices))
    first_dev = devices[0]
    field = next((f for f in first_dev.profile.default_fields() if f in first_dev.fields), None)
    if first and field is not None and not port.startswith("tcp:") and first_dev.address <= 247:
        kind = "3" if field.table is Table.INPUT else "4"
        baud = speed or first_dev.profile.serial.baudrate
        out.append(f"mbpoll -m rtu -b {baud} -P none -0 -1 -a {first_dev.address} "
                   f"-t {kind}:hex -r {field.address} -c {field.words} {port}")
    return out
