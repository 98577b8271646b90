"""``rtupoll doctor``: check the adapter (and, given an address, one device), one line a
finding with its fix. The checks are ``rtupoll.jobs.doctor``'s."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import click

from rtupoll.cli.options import format_option, port_options, profiles_option
from rtupoll.cli.params import Seconds
from rtupoll.errors import PortError, UsageError
from rtupoll.rtu import Table

EPILOG = """\b
Examples:
  rtupoll doctor -p /dev/ttyUSB0                     (the adapter)
  rtupoll doctor -p /dev/ttyUSB0 -b 9600 huiwen-aq@3 (and a device, by its profile)
  rtupoll doctor -p COM3 --address 1                 (a device with no profile)
"""


@click.command(epilog=EPILOG)
@click.argument("device", required=False, metavar="[PROFILE@ADDRESS]")
@port_options
@click.option("--address", "-a", "unit", type=click.IntRange(1, 247), default=None,
              help="Check the device at this address too (no profile: it reads holding "
                   "register 0; any answer, an exception too, counts).")
@click.option("--timeout", type=Seconds(0.01, 30), default=None, metavar="SECONDS",
              help="How long to wait for the device (default: its profile's, else 0.5).")
@format_option("text", "json")
@profiles_option
def doctor(device: str | None, port: str | None, baudrate: int | None, parity: str | None,
           stopbits: str | None, unit: int | None, timeout: float | None, fmt: str,
           profile_dirs: tuple[Path, ...]) -> None:
    """Check the port and its adapter, and a device: one line a finding, with its fix.

    \b
    port      opens as the bus opens it, or why not (busy, permission, missing)
    latency   the USB adapter's latency timer, added to every reply
    rs485     whether the kernel switches an RS-485 transceiver's direction
    echo      whether the adapter echoes what it sends (a request to unit 247)
    With a device (PROFILE@ADDRESS or --address):
    idle-gap  whether it needs a silence on the line before it hears a request
    reply     its reply time, against the timeout
    pauses    pauses inside its replies longer than 1.5 characters

    Exit 3 when the port does not open; otherwise 0, whatever was found.
    """
    from rtupoll.cli.target import load_target, port_settings, run_on_bus
    from rtupoll.jobs.doctor import Doctor, Finding

    profile, table, address, count = None, Table.HOLDING, 0, 1
    if device is not None:
        if unit is not None:
            raise UsageError("give PROFILE@ADDRESS or --address, not both")
        target = load_target(device, profile_dirs)
        profile, unit = target.profile, target.unit
        assert profile is not None
        f = next((profile.field(c.field) for c in profile.identify),
                 profile.fields[0] if profile.fields else None)
        if f is not None and f.table.is_register:
            table, address, count = f.table, f.address, f.words
    settings = port_settings(profile, port, baudrate, parity, stopbits)
    wait = timeout or (profile.limits.timeout if profile else 0.5)
    findings: list[Finding] = []
    framing = settings.framing
    title = (f"{settings.port} at {framing.baudrate} {framing.bytesize}{framing.parity}"
             f"{framing.stopbits:g}")

    async def job(bus: Any) -> list[Finding]:
        found = [Finding("port", "ok", f"opens ({title})")]
        doc = Doctor(bus)
        found += await doc.adapter()
        if unit is not None:
            found += await doc.device(unit, table, address, count, wait)
        return found

    try:
        findings = run_on_bus(settings, job, blocking=True)
    except PortError as exc:  # the one line on stderr says it; a script gets it too
        if fmt == "json":
            _show([Finding("port", "problem", str(exc), _fix(str(exc)))], title, fmt)
        raise
    _show(findings, title, fmt)


def _fix(message: str) -> str:
    """The port error's own advice (after its colon or in its parentheses)."""
    return message.rpartition("(")[2].rstrip(")") if message.endswith(")") else ""


def _show(findings: list[Any], title: str, fmt: str) -> None:
    if fmt == "json":
        for f in findings:
            click.echo(json.dumps(f.record(), ensure_ascii=False))
        return
    click.echo(f"rtupoll doctor: {title}")
    for f in findings:
        click.echo(f"{f.status:<8} {f.check:<9} {f.text}")
        if f.fix:
            click.echo(f"{'':18}fix: {f.fix}")
    sys.stdout.flush()
