"""``rtupoll profiles``: list, show and check device profiles."""

from __future__ import annotations

import json
from pathlib import Path

import click
from rich.console import Console
from rich.table import Table as RichTable

from rtupoll.cli.options import format_option, profiles_option
from rtupoll.errors import ProfileError
from rtupoll.profile import Field, Profile, bundled_dir, load_library, load_one, load_profile


@click.group()
def profiles() -> None:
    """List, show and check device profiles."""


@profiles.command("list")
@profiles_option
@format_option("table", "json")
def list_(profile_dirs: tuple[Path, ...], fmt: str) -> None:
    """Every profile on the search path: user directories first, then the bundled ones."""
    lib = load_library(profile_dirs)
    rows = sorted(lib.profiles.values(), key=lambda p: p.id)
    if fmt == "json":
        for p in rows:
            click.echo(json.dumps({"id": p.id, "vendor": p.vendor, "model": p.model,
                                   "manual": p.manual, "path": p.path,
                                   "bundled": Path(p.path).parent == bundled_dir()}))
        return
    t = RichTable(title="Device profiles")
    for col in ("id", "vendor", "model", "serial", "fields", "source"):
        t.add_column(col)
    for p in rows:
        s = p.serial
        t.add_row(p.id, p.vendor, p.model, f"{s.baudrate} {s.bytesize}{s.parity}{s.stopbits}",
                  str(len(p.fields)),
                  "bundled" if Path(p.path).parent == bundled_dir() else p.path)
    Console().print(t)


@profiles.command("show")
@click.argument("profile_id")
@profiles_option
def show(profile_id: str, profile_dirs: tuple[Path, ...]) -> None:
    """The register map of one profile, with wire and manual addresses."""
    p = load_one(profile_id, profile_dirs)
    console = Console()
    console.print(_summary(p))
    t = RichTable(title=f"{p.id} register map")
    for col in ("field", "table", "wire", "manual", "type", "order", "unit", "scale",
                "access", "poll", "description"):
        t.add_column(col, overflow="fold")
    for f in p.fields:
        t.add_row(f.name, f.table.value, f"0x{f.address:04X}", f.written, _type(f),
                  f.layout.order.value if f.words > 1 else "", f.unit, _scale(f), f.access,
                  f.poll.value, _describe(f))
    console.print(t)


@profiles.command("check")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
def check(files: tuple[Path, ...]) -> None:
    """Validate profile files; print file:line: field: error for each bad one."""
    bad = 0
    for path in files:
        try:
            p = load_profile(path)
        except ProfileError as exc:
            bad += 1
            click.echo(str(exc), err=True)
        else:
            click.echo(f"{path}: ok ({p.id}, {len(p.fields)} fields)")
    if bad:
        raise ProfileError(f"{bad} of {len(files)} profile(s) have errors")


def _summary(p: Profile) -> str:
    s, a, lim = p.serial, p.addresses, p.limits
    lines = [
        f"[bold]{p.id}[/] — {p.vendor} {p.model} ({p.manual})",
        f"serial {s.baudrate} {s.bytesize}{s.parity}{s.stopbits}"
        + (f" (also {', '.join(map(str, s.baudrates))})" if len(s.baudrates) > 1 else "")
        + (", DTR/RTS deasserted" if s.deassert_dtr else ""),
        f"addresses {a.lo}..{a.hi}, default {a.default}"
        + (f", any-device {a.any}" if a.any else "")
        + "".join(f", reserved {k} ({v})" for k, v in a.reserved.items()),
        f"addressing {p.addressing.value}; max {lim.max_registers} registers per read; "
        f"functions {', '.join(f'{f:02d}' for f in sorted(lim.functions))}; "
        f"timeout {lim.timeout:g} s",
        "set-address: " + (
            f"{p.set_address.field} via FC{p.set_address.function:02d}" if p.set_address.field
            else f"not supported ({p.set_address.unsupported})"),
    ]
    if p.notes:
        lines.append(p.notes)
    return "\n".join(lines)


def _type(f: Field) -> str:
    t = f.layout.type.value
    if t == "string":
        return f"string({2 * f.words})"
    if t in ("u8", "i8"):
        return f"{t} {f.layout.byte}"
    return t


def _scale(f: Field) -> str:
    parts = []
    if f.layout.scale != 1:
        parts.append(f"x{f.layout.scale:g}")
    if f.layout.offset:
        parts.append(f"{f.layout.offset:+g}")
    return " ".join(parts)


def _describe(f: Field) -> str:
    text = f.description
    if f.enum:
        text += " [" + ", ".join(f"{c}={ch.name}" for c, ch in f.enum.items()) + "]"
    if f.flags:
        text += " [" + ", ".join(f"0x{m:X}={ch.name}" for m, ch in f.flags.items()) + "]"
    if f.since:
        text += f" (from variant {f.since})"
    if f.source == "public":
        text += " (public source)"
    return text.strip()
