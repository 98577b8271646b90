"""``rtupoll write``: set fields (or raw registers), then read them back and show them.

Every check that needs no device runs before the port is even opened, and on a
terminal the exact change is shown and confirmed; from a script, ``--yes`` is the
confirmation. What is printed afterwards is what the device holds now.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from rtupoll.cli.options import format_option, port_options, profiles_option
from rtupoll.cli.read import Row, emit, raw_options, specs_of
from rtupoll.cli.target import (
    Target,
    confirm,
    confirm_now,
    load_target,
    port_settings,
    run_on_bus,
    speed_note,
    timing_options,
)
from rtupoll.errors import (
    BusError,
    DeviceTimeout,
    FrameError,
    Interrupted,
    PortError,
    RefusedError,
    UsageError,
)
from rtupoll.jobs.device import Timing
from rtupoll.jobs.device import timing as device_timing
from rtupoll.jobs.writes import (
    RAW_FUNCTIONS,
    RawWrite,
    WriteOp,
    plan_raw_write,
    plan_write,
    read_back,
    verify,
    verify_raw,
    write_raw,
)
from rtupoll.jobs.writes import write as write_field
from rtupoll.model.interpret import FieldValue
from rtupoll.model.profile import Field
from rtupoll.rtu import Table


def split_assignment(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise UsageError(f"{text!r} is not FIELD=VALUE (e.g. measurement_1_mode=FBB)")
    return name.strip(), value


def plan_fields(target: Target, assignments: tuple[str, ...]) -> list[WriteOp]:
    """Check every ``FIELD=VALUE`` before anything is sent."""
    p = target.profile
    assert p is not None
    ops = []
    for text in assignments:
        name, value = split_assignment(text)
        if ":" in name:
            raise UsageError(f"{name!r} looks like a register spec: add --raw to write registers")
        field = p.field(name)
        if p.set_address.field == field.name:
            raise RefusedError(f"{name} is the device's own address: use 'rtupoll set-address "
                               f"{target.name} NEW', which verifies the move")
        ops.append(plan_write(field, value, p.limits.functions))
    return ops


@click.command()
@click.argument("device", metavar="DEVICE")
@click.argument("assignments", nargs=-1, required=True, metavar="FIELD=VALUE...")
@port_options
@timing_options
@raw_options
@click.option("--function", "function", type=click.Choice(["6", "16"]), default=None,
              help="--raw: force FC06 or FC16 (default: FC06 for one register when the "
                   "device has it).")
@click.option("--yes", "-y", is_flag=True, help="Do not ask for confirmation (scripts).")
@format_option("table", "json", "csv")
@profiles_option
def write(device: str, assignments: tuple[str, ...], port: str | None, baudrate: int | None,
          parity: str | None, stopbits: str | None, timeout: float | None,
          retries: int | None, raw: bool, addressing: str, type_name: str, order: str | None,
          function: str | None, yes: bool, fmt: str, profile_dirs: tuple[Path, ...]) -> None:
    """Write FIELD=VALUE to DEVICE (PROFILE@ADDRESS), read back and show the result.

    Values are numbers (decimal or 0x hex), enum names, flag names joined with '|',
    or text. Read-only fields and values outside a field's range are refused.

    \b
    rtupoll write -p /dev/ttyUSB0 banner-ez-array@1 measurement_1_mode=TBB
    rtupoll write -p /dev/ttyUSB0 --raw --yes 5 holding:0x0010=1,2,3
    """
    target = load_target(device, profile_dirs, bare_ok=raw)
    if not raw and target.profile is None:
        raise UsageError("a bare address needs --raw")
    if not raw and (addressing != "pdu" or order or type_name != "u16" or function):
        raise UsageError("--one-based, --modicon, --type, --order and --function are for "
                         "--raw writes")
    timing = device_timing(target.profile, timeout, retries)
    sent: list[str] = []  # the writes whose request has gone (or is going) out
    if raw:
        functions = target.profile.limits.functions if target.profile else RAW_FUNCTIONS
        if function:
            functions = frozenset({5, int(function)})
        raws = []
        for text in assignments:
            spec_text, value = split_assignment(text)
            spec = specs_of(target, [spec_text], addressing, type_name, order)[0]
            raws.append(plan_raw_write(spec, value, functions))
            check_move(target, raws[-1])
        confirm(_question(target, [r.describe() for r in raws]), yes)
        settings = port_settings(target.profile, port, baudrate, parity, stopbits)
        how = ([f"--{addressing.replace('_', '-')}"] if addressing != "pdu" else []) + \
            (["--type", type_name] if type_name != "u16" else []) + \
            (["--order", order] if order else [])
        with _applied_if_interrupted(sent, _check(settings.port, target, raws, how)):
            rows = run_on_bus(settings, lambda bus: _raw(bus, target, raws, timing, sent),
                              on_timeout=speed_note(settings, target.profile, baudrate),
                              blocking=True)
    else:
        ops = plan_fields(target, assignments)
        confirm_now(yes)  # refused before the port opens when nobody can confirm
        settings = port_settings(target.profile, port, baudrate, parity, stopbits)

        async def job(bus: Any) -> list[Row]:
            if not yes:  # show what the device holds now, then ask
                now = [await read_back(bus, target.unit, op.field, timing)
                       if "R" in op.field.access else None for op in ops]
                confirm(_question(target, [f"{op.describe()}  (now: {_now(fv)})"
                                           for op, fv in zip(ops, now, strict=True)]), yes)
            return await _fields(bus, target.unit, ops, timing, sent)

        with _applied_if_interrupted(sent, _check(settings.port, target, ops)):
            rows = run_on_bus(settings, job, on_timeout=speed_note(settings, target.profile,
                                                                   baudrate), blocking=True)
    who = target.name if target.profile else f"unit {target.unit}"
    try:
        emit(target, rows, fmt, False, title=f"{who} after writing (read back)")
    except KeyboardInterrupt:  # the writes are done and read back: only the showing stopped
        raise Interrupted(f"interrupted while showing the result: {'; '.join(sent)} "
                          "written and read back") from None


def _now(fv: FieldValue | None) -> str:
    if fv is None:
        return "write-only"
    return f"{fv.text} {fv.field.unit}".strip()


def _question(target: Target, lines: list[str]) -> str:
    return f"Write to {target.name}:\n  " + "\n  ".join(lines) + "\nSend?"


@contextlib.contextmanager
def _applied_if_interrupted(sent: list[str], check: str) -> Iterator[None]:
    """Ctrl-C or SIGTERM, or the port lost, once a write request has gone out: the device
    may have taken it, so say so, and how to know (``check``), as ``set-address`` does
    (exit 130 for an interruption, 3 for the port)."""
    try:
        yield
    except KeyboardInterrupt:
        if not sent:
            raise
        raise Interrupted(f"interrupted after sending {'; '.join(sent)}: the write may have "
                          f"been applied; read the device to know: {check}") from None
    except PortError as exc:
        if not sent:
            raise
        raise PortError(f"{exc}, after sending {'; '.join(sent)}: the write may have been "
                        f"applied; once the port is back, read the device to know: {check}"
                        ) from None


def _check(port: str, target: Target, writes: list[WriteOp] | list[RawWrite],
           how: list[str] | None = None) -> str:
    """The command that reads back what ``writes`` write (``how``: the raw options)."""
    fields = [w.field.name for w in writes if isinstance(w, WriteOp)]
    raws = [w.spec.label(0) + (f":{w.spec.count}" if w.spec.count > 1 else "")
            for w in writes if isinstance(w, RawWrite)]
    what = fields if not raws else ["--raw", *(how or []), *raws]
    return " ".join(["rtupoll", "read", "-p", port, target.name, *what])


async def _fields(bus: Any, unit: int, ops: list[WriteOp], timing: Timing,
                  started: list[str]) -> list[Row]:
    rows: list[Row] = []
    for op in ops:
        started.append(op.describe())
        sent, _ = await write_field(bus, unit, op, timing)  # an echo is checked by the bus
        if "R" not in op.field.access:
            rows.append((op.field, None, "written (write-only: cannot be read back)"))
            continue
        now = await read_back(bus, unit, op.field, timing)
        verify(op, sent, now)
        rows.append((op.field, now, ""))
    return rows


async def _raw(bus: Any, target: Target, raws: list[RawWrite], timing: Timing,
               started: list[str]) -> list[Row]:
    rows: list[Row] = []
    for rw in raws:
        started.append(rw.describe())
        moved = address_register(target, rw)
        if moved is not None:
            rows += await _raw_move(bus, target, rw, moved, timing)
            continue
        await write_raw(bus, target.unit, rw, timing)
        rows += [(fv.field, fv, "") for fv in await verify_raw(bus, target.unit, rw, timing)]
    return rows


def address_register(target: Target, rw: RawWrite) -> tuple[Field, int] | None:
    """The profile's address register and the address written to it, when a raw write
    covers it: such a write moves the device, so it is verified at the new address."""
    p = target.profile
    if p is None or not p.set_address.field or rw.spec.table is not Table.HOLDING:
        return None
    f = p.field(p.set_address.field)
    if not rw.spec.address <= f.address < rw.spec.address + rw.spec.words:
        return None
    return f, rw.words[f.address - rw.spec.address]


def _moves(target: Target, rw: RawWrite, moved: tuple[Field, int]) -> str:
    field, new = moved
    pid = target.profile.id if target.profile else "the device"
    return (f"{rw.spec.label(0)} is {pid}'s address register ({field.name}): writing {new} "
            f"there moves the device to address {new}")


def check_move(target: Target, rw: RawWrite) -> None:
    """A raw write that would move the device somewhere it cannot be reached is refused."""
    moved = address_register(target, rw)
    if moved is None or target.profile is None:
        return
    a, new = target.profile.addresses, moved[1]
    why = a.reserved.get(new) if new in a.reserved else (
        f"outside its range {a.lo}..{a.hi}" if not a.lo <= new <= a.hi or new > 247 else "")
    if why:
        raise RefusedError(f"{_moves(target, rw, moved)}, which is {why}; 'rtupoll "
                           f"set-address {target.name} NEW' checks and verifies the move")


async def _raw_move(bus: Any, target: Target, rw: RawWrite, moved: tuple[Field, int],
                    timing: Timing) -> list[Row]:
    """A raw write to the address register: the reply may come from nowhere (the device
    has moved, or answers the write with a non-echo), so look for it at the new address."""
    what = _moves(target, rw, moved)
    new = moved[1]
    with contextlib.suppress(BusError):  # judged by reading back, like set-address
        await write_raw(bus, target.unit, rw, timing)
    try:
        rows = await verify_raw(bus, new, rw, timing)
    except BusError as exc:
        old = "" if new == target.unit else f" (and no longer at {target.unit})"
        kind = type(exc) if type(exc) in (DeviceTimeout, FrameError) else BusError
        raise kind(f"{what}{old}, but reading it back there failed: {exc}; find it with "
                   f"'rtupoll scan -p {bus.settings.port}'") from None
    click.echo(f"rtupoll: {what}; it answers there now", err=True)
    return [(fv.field, fv, f"device now at address {new}") for fv in rows]
