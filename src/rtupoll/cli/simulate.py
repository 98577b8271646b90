"""``rtupoll simulate``: serve simulated devices on a pseudo-terminal or RTU-over-TCP.

The first thing a newcomer without hardware runs, so its output says what is being
served, where, and what to try next; it runs until Ctrl-C or SIGTERM and exits 0.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

import click

from rtupoll.cli.options import profiles_option
from rtupoll.errors import UsageError
from rtupoll.rtu import Table

if TYPE_CHECKING:
    from rtupoll.sim.runner import SimulatedBus

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
@click.option("--turnaround", type=click.FloatRange(0, 10), default=None, metavar="SECONDS",
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
@click.option("--tick", type=click.FloatRange(0, 3600), default=1.0, show_default=True,
              metavar="SECONDS", help="How often values move; 0 freezes them.")
@click.option("--link", type=click.Path(dir_okay=False), default=None,
              help="Also make this symbolic link to the pty (a stable port name).")
@click.option("--tcp", default=None, metavar="HOST:PORT",
              help="Serve RTU frames over TCP (like a serial gateway) instead of a pty.")
@click.option("--verbose", "-v", is_flag=True, help="Print every frame on the wire.")
@profiles_option
def simulate(devices: tuple[str, ...], baud: int | None, turnaround: float | None,
             scenario: Path | None, sets: tuple[str, ...], options: tuple[str, ...],
             faults: tuple[str, ...], seed: int | None, tick: float, link: str | None,
             tcp: str | None, verbose: bool, profile_dirs: tuple[Path, ...]) -> None:
    """Serve simulated Modbus RTU devices until interrupted.

    Devices are PROFILE@ADDRESS (e.g. net-irnet-pro@1 huiwen-aq@3); with none, one of
    each bundled profile is served. Clients open the printed pty path as a serial port
    (any baud rate), or connect to --tcp.
    """
    from rtupoll.sim.runner import simulated_bus
    from rtupoll.sim.server import WireFrame

    if link and tcp:
        raise UsageError("--link names a pty; it cannot be used with --tcp")
    if tcp is not None and ":" not in tcp:
        raise UsageError(f"--tcp {tcp!r} is not HOST:PORT (e.g. 127.0.0.1:5020)")
    t0 = time.monotonic()

    def show(frame: WireFrame) -> None:
        click.echo(f"{frame.time - t0:10.4f}  {frame}")

    bus: SimulatedBus = simulated_bus(
        devices, baudrate=baud, faults=faults, scenario=scenario, tcp=tcp or False, seed=seed,
        sets=sets, options=options, turnaround=turnaround, tick=tick or None,
        profile_dirs=profile_dirs, link=link, on_wire=show if verbose else None)
    stop = threading.Event()

    caught: list[int] = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        caught.append(signum)
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        bus.start()
        try:
            _banner(bus, link)
            sys.stdout.flush()  # a pipe is block-buffered; whoever reads us needs the port
            while not stop.wait(0.5):
                pass
        finally:
            bus.stop()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    engine = bus.engine
    assert engine is not None
    newline = "\n" if caught[:1] == [signal.SIGINT] else ""  # after the terminal's ^C
    click.echo(f"{newline}stopped after {engine.requests} requests ({engine.replies} replies).")


def _banner(bus: SimulatedBus, link: str | None) -> None:
    c = bus.config
    devices = bus.device_list()
    if bus.port.startswith("tcp:"):
        what = "RTU over TCP, like a serial gateway"
    elif c.baudrate:
        what = f"a serial port: open it at {c.baudrate} baud"
    else:
        what = "a serial port: open it at any baud rate"
    click.echo(f"Simulating {len(devices)} device{'s' if len(devices) != 1 else ''} on "
               + click.style(bus.port, bold=True) + (f", linked as {link}" if link else "")
               + f" ({what})")
    rows = []
    for d in devices:
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
    if c.faults:
        click.echo("  bus faults: " + ", ".join(str(f) for f in c.faults))
    if c.baudrate:
        fr = bus.framing
        assert fr is not None
        click.echo(f"Wire timing: {c.baudrate} baud 8N1 (3.5-character silence "
                   f"{fr.silence * 1000:.2f} ms, plus each device's turnaround).")
    else:
        click.echo("Wire timing: off, replies at once (--baud N for real wire time).")
    click.echo(f"Values move every {c.tick:g} s (seed {c.seed})." if c.tick
               else f"Values are frozen (seed {c.seed}).")
    first = devices[0]
    field = next((f for f in first.profile.default_fields() if f in first.fields), None)
    click.echo("Try:")
    port = link or bus.port
    click.echo(f"  rtupoll read --port {port} {first.profile.id}@{first.address}")
    click.echo(f"  rtupoll poll --port {port} " + " ".join(d.name for d in devices))
    if field is not None and not bus.port.startswith("tcp:") and first.address <= 247:
        kind = "3" if field.table is Table.INPUT else "4"
        baud = c.baudrate or first.profile.serial.baudrate
        click.echo(f"  mbpoll -m rtu -b {baud} -P none -0 -1 "
                   f"-a {first.address} -t {kind}:hex -r {field.address} -c {field.words} "
                   f"{port}")
    click.echo("Press Ctrl-C to stop.")
