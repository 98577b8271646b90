"""``rtupoll set-address``: one device, a plan file, or the interactive field workflow.

The logic (refusals, write, verification, "already done") is in
``rtupoll.jobs.commission``; this module is about the three ways a person drives it and
about reporting, because after a half-finished commissioning run the first thing a
technician needs is what was and was not changed.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from rtupoll.cli.options import format_option, port_options, profiles_option
from rtupoll.cli.target import (
    Target,
    confirm,
    load_target,
    port_settings,
    run_on_bus,
    speed_note,
    timing_options,
)
from rtupoll.config.library import load_library
from rtupoll.errors import PlanFailed, PortError, RtupollError, UsageError
from rtupoll.jobs.commission import (
    Commissioner,
    PlanInterrupted,
    Presence,
    Result,
    Status,
    cut_off,
    cut_short,
    dry_run,
    run_plan,
)
from rtupoll.model.addressing import Change, address_field, refuse, shared_reserved
from rtupoll.model.profile import Profile
from rtupoll.numbers import parse_unit
from rtupoll.ui.records import json_safe

if TYPE_CHECKING:
    import asyncio


@click.command("set-address")
@click.argument("device", required=False, metavar="[DEVICE]")
@click.argument("new", required=False, metavar="[NEW]")
@port_options
@timing_options
@click.option("--plan", "plan_file", type=click.Path(dir_okay=False, path_type=Path),
              help="Run the changes of a CSV or YAML plan, in order (see docs/commands.md).")
@click.option("--interactive", "-i", is_flag=True,
              help="Field workflow: connect each new sensor (at DEVICE's address), press "
                   "Enter, and it gets the next free address from NEW on.")
@click.option("--dry-run", is_flag=True, help="Print the frames that would be sent; send none.")
@click.option("--yes", "-y", is_flag=True, help="Do not ask for confirmation (scripts).")
@click.option("--allow-reserved", is_flag=True,
              help="Allow addresses other device models reserve on a shared bus (0xCC, 0xFE "
                   "for CO2Meter boards) when none of them is on this bus.")
@format_option("text", "json")
@profiles_option
def set_address(device: str | None, new: str | None, port: str | None, baudrate: int | None,
                parity: str | None, stopbits: str | None, timeout: float | None,
                retries: int | None, plan_file: Path | None, interactive: bool, dry_run: bool,
                yes: bool, allow_reserved: bool, fmt: str, profile_dirs: tuple[Path, ...]
                ) -> None:
    """Give DEVICE (PROFILE@ADDRESS) the address NEW, and verify it moved.

    Refused (exit 8) when NEW is reserved or outside the device's range, when
    something already answers at NEW, or when the profile has no documented way
    to change the address. A row already done (answering at NEW, not at the old
    address) is reported and skipped, so plans can be re-run.

    \b
    rtupoll set-address -p /dev/ttyUSB0 huiwen-aq@1 12
    rtupoll set-address -p /dev/ttyUSB0 --plan sensors.csv --yes
    rtupoll set-address -p /dev/ttyUSB0 --interactive radar-level@1 10
    """
    avoid = {} if allow_reserved else shared_reserved(load_library(profile_dirs).profiles.values())

    def settings(profile: Profile) -> Any:
        return port_settings(profile, port, baudrate, parity, stopbits)

    def commissioner(bus: Any) -> Commissioner:
        return Commissioner(bus, timeout=timeout, retries=retries,
                            log=lambda m: click.echo(f"  {m}", err=True))

    if plan_file is not None:
        if device or new or interactive:
            raise UsageError("--plan takes no DEVICE or NEW (they are in the plan's rows)")
        from rtupoll.config.address_plan import load_plan

        changes = load_plan(plan_file, profile_dirs, avoid)
        if dry_run:
            return _dry_run(changes)
        _same_serial(changes, baudrate)
        confirm(f"Change {len(changes)} address(es) per {plan_file}?", yes)
        return _plan(changes, settings(changes[0].profile), commissioner, fmt)
    if not device:
        raise UsageError("give DEVICE and NEW, --plan FILE, or --interactive DEVICE [FIRST]")
    target = load_target(device, profile_dirs)
    assert target.profile is not None
    if interactive:
        if dry_run:
            raise UsageError("--dry-run shows one change or a plan, not an interactive session")
        first = _address(new) if new else None
        return _interactive(target, first, settings(target.profile), commissioner, avoid)
    if new is None:
        raise UsageError("missing NEW: the address to give the device")
    change = Change(target.profile, target.unit, _address(new), avoid=avoid)
    if dry_run:
        return _dry_run([change])
    refuse(change)
    confirm(f"Change the address of {target.name} to {change.new}?", yes)
    on = settings(target.profile)
    ran: list[Commissioner] = []

    def job(bus: Any) -> Awaitable[Result]:
        ran.append(commissioner(bus))
        return ran[-1].apply(change)

    # cut short once the write may be out, the device may be at either address: say so
    again = f"run 'rtupoll set-address -p {port} {change.profile.id}@{change.old} " \
        f"{change.new}' again"
    try:
        result = run_on_bus(on, job, on_timeout=speed_note(on, target.profile, baudrate))
    except KeyboardInterrupt:
        _one(cut_short(change, bool(ran) and ran[-1].sent is change, again), fmt)
        raise
    except PortError as exc:
        if not (ran and ran[-1].sent is change):
            raise
        lost = PortError(cut_off(change, exc, again))
        if fmt == "json":  # the record too, as for an interruption
            _one(Result(change, Status.FAILED, str(lost), lost), fmt)
        raise lost from None
    _one(result, fmt)


def _one(result: Result, fmt: str) -> None:
    """A single change's outcome: its line, or its JSON record (as a plan's row)."""
    if fmt == "json":
        _reporter(fmt)(result)
    else:
        click.echo(f"{result.change.label}: {result.detail}")


def _plan(changes: list[Change], settings: Any, commissioner: Callable[[Any], Commissioner],
          fmt: str) -> None:
    """Run the rows, reporting each as it ends; then fail with the first failure's code."""
    report = _reporter(fmt)
    asks = _next_sensor(changes) if sys.stdin.isatty() else None
    try:
        results = run_on_bus(settings,
                             lambda bus: run_plan(commissioner(bus), changes, report, asks))
    except PlanInterrupted as exc:  # every row was reported; the summary, then exit 130
        _summary(exc.results, fmt)
        raise
    _summary(results, fmt)
    for row, result in enumerate(results, 1):
        if result.error is not None:
            raise PlanFailed(row, result.error)


def _next_sensor(changes: list[Change]) -> Callable[[Change, bool], Awaitable[bool]]:
    """On a terminal, a shared row whose sensor is not there yet asks for it."""
    rows = {id(c): n for n, c in enumerate(changes, 1)}

    async def ask(change: Change, again: bool) -> bool:
        if again:
            click.echo(f"No sensor answers at {change.old}: check its wiring and power.",
                       err=True)
        click.echo(f"Connect the sensor for row {rows[id(change)]} ({change.profile.id}, to "
                   f"become {change.new}) alone at address {change.old}, then press Enter "
                   "(q to stop): ", nl=False, err=True)
        line = sys.stdin.readline()  # the bus is idle: nothing else runs meanwhile
        return bool(line) and line.strip().lower() not in ("q", "quit", "exit")

    return ask


def _address(text: str) -> int:
    try:
        return parse_unit(text)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _dry_run(changes: list[Change]) -> None:
    frames = [dry_run(change) for change in changes]  # refusals first, before any output
    click.echo("Dry run: nothing is sent. '??' marks bytes that depend on a value read first.")
    shared = sorted({c.old for c in changes if c.shared})
    for old in shared:
        rows = [n for n, c in enumerate(changes, 1) if c.old == old]
        click.echo(f"Rows {', '.join(map(str, rows))} each expect a device at {old}: connect "
                   "them one at a time. On a terminal the plan asks for each in turn; "
                   "otherwise run it again after connecting the next (the rows done are "
                   "verified and skipped).")
    for change, steps in zip(changes, frames, strict=True):
        click.echo(f"{change.label}" + (f" ({change.where})" if change.where else ""))
        for frame, why in steps:
            click.echo(f"  {frame:<35} {why}")


def _same_serial(changes: list[Change], baudrate: int | None) -> None:
    """One bus has one baud rate: the rows' profiles must agree, or --baudrate decides."""
    if baudrate:
        return
    rates = {c.profile.id: c.profile.serial.baudrate for c in changes}
    if len(set(rates.values())) > 1:
        listed = ", ".join(f"{p} {b}" for p, b in rates.items())
        raise UsageError(f"the plan's profiles default to different baud rates ({listed}): "
                         "give --baudrate (one bus has one)")


def _reporter(fmt: str) -> Callable[[Result], None]:
    row = 0

    def report(result: Result) -> None:
        nonlocal row
        row += 1
        if fmt == "json":
            click.echo(json.dumps(json_safe(result.record(row)), ensure_ascii=False,
                                  allow_nan=False))
        else:
            mark = {Status.CHANGED: "ok  ", Status.DONE: "skip", Status.FAILED: "FAIL",
                    Status.UNVERIFIED: "????", Status.NOT_RUN: "----"}[result.status]
            click.echo(f"{mark} {result.change.label}: {result.detail}")
        sys.stdout.flush()

    return report


def _summary(results: list[Result], fmt: str) -> None:
    if fmt == "json":
        return
    counts = {s: sum(r.status is s for r in results) for s in Status}
    click.echo(", ".join(f"{n} {s.value}" for s, n in counts.items() if n)
               + f" ({len(results)} row{'s' if len(results) != 1 else ''})")


def _interactive(target: Target, first: int | None, settings: Any,
                 commissioner: Callable[[Any], Commissioner], avoid: Mapping[int, str]
                 ) -> None:
    """Connect a sensor, press Enter, it gets the next free address; a summary as it goes."""

    from rtupoll.io.bus import Bus

    profile, old = target.profile, target.unit
    assert profile is not None
    address_field(profile)  # refused up front when the profile has no address method
    lo = profile.addresses.lo
    start = first if first is not None else (lo + 1 if lo == old else lo)
    from rtupoll import aio

    loop = aio.new_loop()
    bus = Bus(settings)
    done: list[int] = []
    failures: list[RtupollError] = []
    click.echo(f"Commissioning {profile.id} sensors: each new one is expected at address {old}"
               f" and gets the next free address from {start}.")
    try:
        loop.run_until_complete(bus.open())
        com = commissioner(bus)
        while True:
            click.echo("Connect the next new sensor and press Enter (q to finish): ", nl=False)
            line = sys.stdin.readline()
            if not line or line.strip().lower() in ("q", "quit", "exit"):
                click.echo("")
                break
            try:
                if loop.run_until_complete(com.presence(profile, old)) is Presence.SILENT:
                    click.echo(f"No sensor answers at {old}: check its wiring and power, then "
                               "press Enter again.\n")
                    continue
                skip = {old, *done, *avoid}
                new = loop.run_until_complete(com.next_free(profile, start, skip))
                result = loop.run_until_complete(com.apply(Change(profile, old, new,
                                                                  avoid=avoid)))
            except RtupollError as exc:
                failures.append(exc)
                click.echo(f"FAIL {exc}")
            else:
                done.append(new)
                start = new + 1
                click.echo(f"ok   {profile.id}@{old} -> {new}: {result.detail}")
                click.echo("     Label this sensor " + click.style(str(new), bold=True) + ".")
            click.echo(_running(done, failures))
            click.echo("")
    except KeyboardInterrupt:
        click.echo("")
        click.echo(_running(done, failures))
        raise
    finally:
        _shutdown(loop, bus)
    if failures:
        raise failures[-1]


def _shutdown(loop: asyncio.AbstractEventLoop, bus: Any) -> None:
    """Cancel what Ctrl-C interrupted (it may hold the bus), then close the port."""
    import asyncio

    pending = asyncio.all_tasks(loop)
    for task in pending:
        task.cancel()
    if pending:
        loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
    loop.run_until_complete(bus.close())
    loop.close()


def _running(done: list[int], failures: list[RtupollError]) -> str:
    text = f"So far: {len(done)} sensor{'s' if len(done) != 1 else ''} readdressed"
    if done:
        text += f" ({', '.join(map(str, done))})"
    if failures:
        text += f", {len(failures)} failed attempt{'s' if len(failures) != 1 else ''}"
    return text + "."
