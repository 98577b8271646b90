"""``rtupoll scan``: find and identify the devices on a bus, and write a site file for them.

The sweep logic lives in ``rtupoll.jobs.scan``; this module parses the options, opens the
port once per serial setting, shows progress on a terminal, and prints what was found,
also when interrupted (Ctrl-C shows the results so far, then exits 130).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from rtupoll.cli.options import format_option, line_options, profiles_option
from rtupoll.cli.params import Seconds
from rtupoll.config.library import load_library
from rtupoll.errors import DeviceTimeout, UsageError
from rtupoll.io.latency import latency_timer, latency_warning
from rtupoll.jobs.scan import (
    LATENCY,
    Found,
    Read,
    Setting,
    default_baudrates,
    default_margin,
    every_speed,
    merged,
    once_each,
    parse_addresses,
    parse_list,
    presence_probes,
    probe_timeout,
    skipped,
    sweep,
    sweep_time,
)
from rtupoll.model.profile import Profile
from rtupoll.model.raw import parse_spec
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.io.bus import Bus

EPILOG = """\b
Examples:
  rtupoll scan --port /dev/ttyUSB0
  rtupoll scan -p /dev/ttyUSB0 --addresses 1-20,100 --baudrate 9600,19200 --parity N,E
  rtupoll scan -p /dev/ttyUSB0 --baudrate 9600 --write-config site.yaml
  rtupoll poll --config site.yaml
"""


@click.command(epilog=EPILOG)
@click.option("--port", "-p", envvar="RTUPOLL_PORT",
              help="Serial port, or tcp://HOST:PORT for an RTU-over-TCP gateway. Also "
                   "$RTUPOLL_PORT.")
@click.option("--addresses", "-a", default="1-247", show_default=True,
              help="Addresses to probe: ranges and single addresses, e.g. 1-20,100.")
@click.option("--baudrate", "-b", "baudrates", default=None,
              help="Baud rates to try, in order, e.g. 9600,19200 (default: every rate a "
                   "library profile runs at, the most common first).")
@click.option("--parity", "parities", default="N", show_default=True,
              help="Parities to try, e.g. N,E.")
@click.option("--include-any", is_flag=True,
              help="Also probe broadcast 0, 'any device' addresses (0xFE: every CO2Meter "
                   "board answers it) and addresses a profile reserves (0xCC).")
@click.option("--first", is_flag=True,
              help="Stop after the first serial setting at which a device was identified.")
@click.option("--turnaround", type=Seconds(0, 10), default=None,
              help="Seconds to allow a device (and the adapter) beyond the wire time "
                   "before an address counts as empty (default: the library's slowest "
                   "typical turnaround + 20 ms).")
@click.option("--probe", "extra_probes", multiple=True, metavar="TABLE:ADDRESS[:COUNT]",
              help="An extra presence probe for devices that stay silent on the default "
                   "one (repeatable; each costs one more timeout per empty address).")
@click.option("--write-config", type=click.Path(dir_okay=False, path_type=Path),
              help="Write the identified devices as a site file for 'rtupoll poll --config'.")
@line_options
@profiles_option
@format_option("table", "json")
def scan(port: str | None, addresses: str, baudrates: str | None, parities: str, include_any: bool,
         first: bool, turnaround: float | None, extra_probes: tuple[str, ...],
         write_config: Path | None, profile_dirs: tuple[Path, ...], fmt: str) -> None:
    """Find every device that answers on a bus and identify it by profile.

    Each address is sent one presence probe per serial setting; anything that answers
    (a reply, an exception, even a garbled frame) is asked the identify questions of
    the profile library. A device no profile explains is listed as unknown, with what
    it answered. Timeouts are derived from the baud rate, so an empty address costs
    a few wire times, not a second.
    """
    from rtupoll.cli.target import need_port

    port = need_port(port)
    library = sorted(load_library(profile_dirs).profiles.values(), key=lambda p: p.id)
    wanted = parse_addresses(addresses)
    skip: dict[int, str] = {} if include_any else skipped(wanted, library)
    units = [a for a in wanted if a not in skip]
    rates = [int(r) for r in parse_list(baudrates, "baud rate", int)] if baudrates \
        else default_baudrates(library)
    pars = [p.upper() for p in parse_list(parities, "parity", _parity)]
    settings = [Setting(r, p) for r in rates for p in pars]
    probes = presence_probes(library) + [_probe(t) for t in extra_probes]
    margin = default_margin(library) if turnaround is None else turnaround
    latency = latency_timer(port)  # a USB adapter's latency timer, when it is one
    if latency is not None and turnaround is None:  # beyond what the margin allows for
        margin += max(0.0, latency - LATENCY)
    warning = latency_warning(port, latency)
    if warning:
        click.echo(warning, err=True)
    if not units or not settings:
        raise UsageError("nothing to scan: no addresses or no serial settings left")

    for a, why in skip.items():
        click.echo(f"skipping {a} (0x{a:02X}): {why}; --include-any probes it", err=True)
    per = ", ".join(f"{1000 * sum(probe_timeout(s.framing, n, margin) for *_, n in probes):.0f}"
                    f" ms at {s.baudrate}" for s in settings[:6])
    click.echo(f"scanning {len(units)} address(es) at {len(settings)} setting(s); timeout per "
               f"address {per}; at least {sweep_time(settings, len(units), probes, margin):.1f} s "
               "if nothing answers", err=True)

    found: list[Found] = []
    echoed: list[bool] = []  # a bus found the adapter echoing (and consumed the echoes)
    try:
        from rtupoll import aio

        aio.run(_run(port, settings, units, library, probes, margin, found, first, echoed))
    except KeyboardInterrupt:
        click.echo("interrupted: the results so far", err=True)
        _report(merged(found), fmt)
        raise
    if any(echoed):
        from rtupoll.rtu.line import ECHO_FOUND

        click.echo(f"rtupoll: {port}: {ECHO_FOUND}", err=True)
    results = merged(found)
    if every_speed(results, settings):
        tried = ", ".join(str(r) for r in dict.fromkeys(s.baudrate for s in settings))
        click.echo(f"every device answered at every baud rate scanned ({tried}): this port "
                   "answers at any speed (a simulator without wire timing, or a gateway that "
                   "sets the line's speed itself), so each is listed once", err=True)
        results = once_each(results)
    _report(results, fmt)
    if not results:
        raise DeviceTimeout(nothing_found(settings, library))
    ids = sum(f.profile is not None for f in results)
    click.echo(f"{ids} identified, {len(results) - ids} unknown or garbled", err=True)
    if write_config is not None:
        _write(write_config, port, results, profile_dirs)
    elif ids:
        click.echo("next: add --write-config site.yaml, then: rtupoll poll --config site.yaml",
                   err=True)


async def _run(port: str, settings: Sequence[Setting], units: Sequence[int],
               library: Sequence[Profile], probes: Sequence[Read], margin: float,
               found: list[Found], first: bool, echoed: list[bool]) -> None:
    from rtupoll.cli.target import line_settings
    from rtupoll.io.bus import Bus, PortSettings

    buses: list[Bus] = []

    def open_bus(s: Setting) -> Bus:
        # DTR/RTS deasserted: a CO2Meter board is held in reset while DTR is asserted.
        # No drain after a timeout beyond the inter-frame silence: the bus never takes
        # a late reply from one unit for another's, and a drain per empty address
        # would double the time of a sweep. An adapter's echo found without --echo is
        # consumed from then on, as poll does (said once, after the sweep).
        bus = Bus(PortSettings(port=port, baudrate=s.baudrate, parity=s.parity,
                               deassert_dtr=True, **line_settings()), drain=0.0)
        bus.line.adopt_echo = True
        buses.append(bus)
        return bus

    try:
        await _sweep(open_bus, settings, units, library, probes, margin, found, first)
    finally:
        echoed.extend(b.echo_found for b in buses)


async def _sweep(open_bus: Callable[[Setting], Bus], settings: Sequence[Setting],
                 units: Sequence[int], library: Sequence[Profile], probes: Sequence[Read],
                 margin: float, found: list[Found], first: bool) -> None:

    if not sys.stderr.isatty():
        await sweep(open_bus, settings, units, library, margin=margin, probes=probes,
                    found=found, first=first)
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    console = Console(stderr=True)
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), TextColumn("{task.fields[found]} found"),
                  console=console, transient=True) as bar:
        task = bar.add_task("scanning", total=len(settings) * len(units), found=0)
        seen = 0

        def progress(s: Setting, unit: int) -> None:
            nonlocal seen
            for f in found[seen:]:
                what = (f.profile.id + ("" if f.profile.provenance.verified else
                                        " (profile unverified)")) if f.profile else f.status
                console.print(f"  {f.address:>3} at {f.setting}: {what}", highlight=False)
            seen = len(found)
            bar.update(task, advance=1, found=len(found), description=f"{s} address {unit:>3}")

        await sweep(open_bus, settings, units, library, margin=margin, probes=probes,
                    found=found, progress=progress, first=first)


def _report(results: Sequence[Found], fmt: str) -> None:
    if fmt == "json":
        for f in results:
            click.echo(to_json(record(f)))
        return
    from rich import box
    from rich.console import Console
    from rich.table import Table as RichTable
    from rich.text import Text

    addresses = len({f.address for f in results})
    t = RichTable(title=f"{addresses} address(es) answered" + (
        f", {len(results)} answers at several settings" if len(results) > addresses else ""),
        title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False)
    t.add_column("address", justify="right", no_wrap=True)
    t.add_column("serial", no_wrap=True)
    t.add_column("profile  (device)", ratio=2)
    t.add_column("evidence / answers", ratio=3)
    for f in results:
        p = f.profile
        what = Text(p.id, style="bold") + Text(f"\n{p.vendor} {p.model}", style="dim") \
            + Text("\nprofile " + p.provenance.label,
                   style="dim" if p.provenance.verified else "bold red") if p \
            else Text(f.status, style="yellow") + Text(
                "\nwrong speed, or two devices answering?" if f.garbled
                else "\nno profile matches", style="dim")
        t.add_row(str(f.address), str(f.setting), what,
                  Text("\n".join(f.evidence if p else f.answers)))
    Console().print(t)


def record(f: Found) -> dict[str, Any]:
    """One found device as JSON; the keys are documented in docs/scan.md."""
    p = f.profile
    return {"address": f.address, "baudrate": f.setting.baudrate, "parity": f.setting.parity,
            "status": f.status, "profile": p.id if p else None,
            "vendor": p.vendor if p else None, "model": p.model if p else None,
            "verification": p.provenance.level.value if p else None,
            "evidence": f.evidence, "answers": f.answers}


def _write(path: Path, port: str, results: Sequence[Found], dirs: Sequence[Path]) -> None:
    text, notes = site_yaml(port, results, [d.resolve() for d in dirs], str(path))
    for n in notes:
        click.echo(f"{path}: {n}", err=True)
    if text is None:
        raise UsageError(f"not writing {path}: no device was identified")
    path.write_text(text, encoding="utf-8")
    click.echo(f"wrote {path}; poll it with: rtupoll poll --config {path}", err=True)


def _probe(text: str) -> Read:
    spec = parse_spec(text)
    return (spec.table, spec.address, spec.words)


def nothing_found(settings: Sequence[Setting], library: Sequence[Profile]) -> str:
    """Why a scan found nothing, in one line: the speeds and parities tried, and the
    settings not tried that the library's devices run at (parity first: many meters
    run 8E1, and a scan at N never hears them)."""
    rates = list(dict.fromkeys(s.baudrate for s in settings))
    pars = list(dict.fromkeys(s.parity for s in settings))
    text = (f"no device answered at any address at {', '.join(map(str, rates))} baud, "
            f"parity {', '.join(pars)}")
    others = [p for p in ("N", "E", "O") if p not in pars]
    if not others:
        return text
    runs: dict[str, list[str]] = {}
    for prof in library:
        if prof.serial.parity not in pars:
            runs.setdefault(prof.serial.parity, []).append(prof.id)
    said = "; ".join(f"{', '.join(ids[:3])}{' ...' if len(ids) > 3 else ''} run at "
                     f"parity {p}" for p, ids in runs.items())
    return (f"{text}; not tried: parity {', '.join(others)}"
            + (f" ({said}: add --parity {','.join([*pars, *runs])})" if runs else ""))


def _parity(text: str) -> str:
    if text.upper() not in ("N", "E", "O"):
        raise ValueError(text)
    return text


def site_yaml(port: str, results: Sequence[Found], dirs: Sequence[Path],
              name: str = "site.yaml") -> tuple[str | None, list[str]]:
    """The site file for the identified devices, and notes on what was left out and why.

    One port is one bus at one speed, so the setting with the most identified devices
    that can run at it is written; devices found at other settings, or whose profile
    cannot run at this one, become comments (a site file that does not load helps
    nobody).
    """
    ids = [f for f in results if f.profile is not None]
    if not ids:
        return None, []
    counts: dict[Setting, int] = {}
    for f in ids:
        assert f.profile is not None
        runs = f.setting.baudrate in f.profile.serial.baudrates \
            and f.setting.parity == f.profile.serial.parity
        counts[f.setting] = counts.get(f.setting, 0) + (1 if runs else 0)
    best = max(counts, key=lambda s: counts[s])
    keep: list[Found] = []
    left: list[str] = []
    for f in results:
        p = f.profile
        where = f"{f.address} ({f.setting})"
        if p is None:
            left.append(f"{f.status} device at {where}: {'; '.join(f.answers)}")
        elif f.setting != best:
            left.append(f"{p.id} at {where}: another serial setting than this bus")
        elif best.baudrate not in p.serial.baudrates or best.parity != p.serial.parity:
            left.append(f"{p.id} at {where}: its profile runs at "
                        f"{', '.join(map(str, p.serial.baudrates))} 8{p.serial.parity}1")
        elif (why := p.addresses.check(f.address)) is not None:
            left.append(f"{p.id} at {where}: {why}")
        elif any(k.address == f.address for k in keep):
            left.append(f"{p.id} at {where}: address already taken")
        else:
            keep.append(f)
    if not keep:
        return None, [f"left out: {n}" for n in left]
    lines = [f"# Written by 'rtupoll scan' on {port}: {len(keep)} device(s) at {best}.",
             "# Name the devices, choose fields and intervals, then:",
             f"#   rtupoll poll --config {name}"]
    if dirs:
        lines.append("profiles: [" + ", ".join(json.dumps(str(d)) for d in dirs) + "]")
    lines += ["buses:", "  - name: line1", f"    port: {json.dumps(port)}",
              f"    baudrate: {best.baudrate}", f"    parity: {best.parity}", "    devices:"]
    lines += [f"      - {{profile: {f.profile.id}, address: {f.address}}}  # "
              f"{f.profile.vendor} {f.profile.model}" for f in keep if f.profile]
    if left:
        lines.append("# Found but not written:")
        lines += [f"#   {n}" for n in left]
    return "\n".join(lines) + "\n", [f"left out: {n}" for n in left]
