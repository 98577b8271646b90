"""``rtupoll profiles``: list, search, show, check and import device profiles."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from rtupoll.cli.options import format_option, profiles_option
from rtupoll.config.library import load_library, load_one, load_profile
from rtupoll.config.paths import bundled_dir
from rtupoll.errors import ProfileError, RtupollError, UsageError
from rtupoll.model.profile import Choice, Field, Profile

if TYPE_CHECKING:  # rich loads only where a table for people is printed: not for --format json
    from rich.text import Text


@click.group()
def profiles() -> None:
    """List, search, show, check and import device profiles."""


@profiles.command("list")
@profiles_option
@format_option("table", "json")
def list_(profile_dirs: tuple[Path, ...], fmt: str) -> None:
    """Every profile on the search path (user directories first, then the bundled ones),
    grouped by kind of device and vendor."""
    _print_profiles(list(load_library(profile_dirs).profiles.values()), fmt,
                    "Device profiles")


@profiles.command("search")
@click.argument("text")
@profiles_option
@format_option("table", "json")
def search(text: str, profile_dirs: tuple[Path, ...], fmt: str) -> None:
    """Profiles whose id, vendor, model, kind or manual, or one of whose field names or
    descriptions, contain TEXT (any case). Exit 2 when none does.

    \b
    rtupoll profiles search eastron
    rtupoll profiles search "solar charge"
    rtupoll profiles search humidity        # devices with a humidity field
    """
    found = [(p, why) for p in load_library(profile_dirs).profiles.values()
             if (why := matches(p, text))]
    if not found:
        raise UsageError(f"no profile matches {text!r}; 'rtupoll profiles list' shows them all")
    _print_profiles([p for p, _ in found], fmt, f"Profiles matching {text!r}",
                    {p.id: why for p, why in found})


@profiles.command("import")
@click.argument("file", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("-o", "--output", "out", type=click.Path(path_type=Path, file_okay=False),
              default=Path("imported"), show_default=True,
              help="Directory for the profiles and site.yaml (created if needed).")
def import_(file: Path, out: Path) -> None:
    """Convert a Home Assistant 'modbus:' YAML configuration, or a Telegraf
    [[inputs.modbus]] request-style configuration (FILE ending .toml or .conf), into
    profiles (one per hub and slave) and a site file for 'rtupoll poll --config'. What
    cannot be converted is listed on stderr as FILE:LINE: path: why; the rest is written.

    \b
    rtupoll profiles import configuration.yaml -o site/
    rtupoll profiles import telegraf.conf -o site/
    rtupoll poll --config site/site.yaml --once
    """
    if file.suffix in (".toml", ".conf"):
        from rtupoll.config.telegraf_import import import_telegraf

        result = import_telegraf(file)
    else:
        from rtupoll.config.ha_import import import_ha

        result = import_ha(file)
    for line in result.report:
        click.echo(line, err=True)
    if not result.profiles:
        raise UsageError(f"{file}: nothing could be converted")
    _write_checked(file, result.profiles, result.site, out)
    click.echo(f"{len(result.profiles)} profile(s), {result.converted} field(s) written to "
               f"{out}/; {len(result.report)} note(s) above; poll with: rtupoll poll "
               f"--config {out / 'site.yaml'}")


def _write_checked(source: Path, profiles: dict[str, str], site: str, out: Path) -> None:
    """Write the import where it is meant to go only once every file of it loads: a
    profile the import got wrong is its bug, reported against the source, never left
    behind half-written."""
    import shutil
    import tempfile

    from rtupoll.config.site import load_site

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".rtupoll-import-", dir=out.parent))
    try:
        for pid, text in profiles.items():
            (tmp / f"{pid}.yaml").write_text(text, encoding="utf-8")
        (tmp / "site.yaml").write_text(site, encoding="utf-8")
        try:
            for pid in profiles:
                load_profile(tmp / f"{pid}.yaml")
            load_site(tmp / "site.yaml")
        except ProfileError as exc:
            what = f"{exc.path}: {exc.message}" if exc.path else exc.message
            raise ProfileError(f"the import of this file made a profile rtupoll cannot load "
                               f"({what}); nothing was written", file=str(source)) from None
        out.mkdir(parents=True, exist_ok=True)
        for item in tmp.iterdir():
            shutil.move(str(item), out / item.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def matches(p: Profile, text: str) -> str:
    """Why a profile matches a search (empty: it does not)."""
    needle = text.lower()
    for what, value in (("id", p.id), ("vendor", p.vendor), ("kind", p.kind),
                        ("model", p.model), ("manual", p.manual),
                        ("source", " ".join(d.title for d in p.provenance.sources))):
        if needle in value.lower():
            return what
    names = [f.name for f in p.fields if needle in f.name or needle in f.description.lower()
             or needle in f.label.lower()]
    return f"field {', '.join(names[:3])}" + (" ..." if len(names) > 3 else "") if names else ""


def _print_profiles(rows: list[Profile], fmt: str, title: str,
                    why: dict[str, str] | None = None) -> None:
    rows = sorted(rows, key=lambda p: (p.kind or "~", p.vendor.lower(), p.id))
    if fmt == "json":
        for p in rows:
            rec = {"id": p.id, "vendor": p.vendor, "model": p.model, "kind": p.kind,
                   "manual": p.manual, "verification": p.provenance.level.value,
                   "sources": [str(d) for d in p.provenance.sources], "path": p.path,
                   "bundled": Path(p.path).parent == bundled_dir()}
            if why is not None:
                rec["match"] = why[p.id]
            click.echo(json.dumps(rec, ensure_ascii=False))
        return
    from rich import box
    from rich.console import Console
    from rich.table import Table as RichTable
    from rich.text import Text
    console = Console()
    user = [p for p in rows if Path(p.path).parent != bundled_dir()]
    extra = "matches" if why is not None else "from" if user else ""
    # one line a profile at 80 columns: the id, what a search matched and the short
    # columns keep their width, the device's name gives way ('profiles show' has it
    # whole), and a narrow search leaves out serial settings and field counts
    wide = not extra or console.width >= 100
    kinds = {p.kind or "other" for p in rows}
    columns: list[tuple[str, int, dict[str, Any]]] = [
        ("kind / id", max(*(len(p.id) + 2 for p in rows), *map(len, kinds)),
         {"style": "bold"})]
    if wide:
        columns += [("serial", 10, {}), ("fields", 6, {"justify": "right"})]
    columns.append(("verified", 10, {}))
    if extra:
        columns.append((extra, max(len(why[p.id] if why is not None else "bundled"
                                       if p not in user else p.path) for p in rows), {}))
    t = RichTable(title=title, box=box.SIMPLE_HEAD, pad_edge=False)
    for n, (name, width, style) in enumerate(columns):
        t.add_column(name, no_wrap=True, min_width=width, **style)
        if not n:
            t.add_column("device", no_wrap=True, overflow="ellipsis")
    kind = None
    for p in rows:
        if p.kind != kind:
            kind = p.kind
            t.add_row(Text(kind or "other", style="bold underline"))
        s = p.serial
        cells: list[str | Text] = ["  " + p.id, f"{p.vendor} {p.model}"]
        if wide:
            cells += [f"{s.baudrate} {s.bytesize}{s.parity}{s.stopbits}", str(len(p.fields))]
        cells.append(level_text(p))
        if why is not None:
            cells.append(why[p.id])
        elif user:
            cells.append("bundled" if p not in user else p.path)
        t.add_row(*cells)
    device = t.columns[1]
    device.width = 0  # what the other columns, their padding and the edges leave
    device.width = max(console.width - console.measure(t).maximum, 10)
    console.print(t)


@profiles.command("show")
@click.argument("profile_id")
@profiles_option
def show(profile_id: str, profile_dirs: tuple[Path, ...]) -> None:
    """The register map of one profile: wire and manual addresses, types, units, codes.

    Tables are abbreviated as for 'read --raw': co coil, di discrete input, ir input
    register, hr holding register.
    """
    from rich import box
    from rich.console import Console
    from rich.table import Table as RichTable
    from rich.text import Text
    p = load_one(profile_id, profile_dirs)
    console = Console()
    console.print(_summary(p), highlight=False)
    narrow = console.width < 110  # descriptions under the names, so addresses stay whole
    t = RichTable(title=f"{p.id} register map", title_justify="left", box=box.SIMPLE_HEAD,
                  pad_edge=False)
    t.add_column("field" + ("  (description)" if narrow else ""), no_wrap=not narrow,
                 style="bold", ratio=1 if narrow else None)
    t.add_column("where" if p.addressing.value == "pdu" else "where  (= on the wire)",
                 no_wrap=True)
    t.add_column("type", no_wrap=True)
    t.add_column("unit", no_wrap=True)
    t.add_column("R/W", no_wrap=True)
    if not narrow:
        t.add_column("description", ratio=1)
    for f in p.fields:
        where = f"{_TABLE[f.table.value]} {f.written}"
        if f.written.split(" ")[0] != f"0x{f.address:04X}":
            where += f" = 0x{f.address:04X}"
        cells = [where, _type(f), _unit(f), f.access]
        desc = _describe(f)
        if narrow:
            t.add_row(Text(f.name, style="bold") + (Text("\n" + desc, style="dim not bold")
                                                     if desc else Text()), *cells)
        else:
            t.add_row(f.name, *cells, Text(desc))
    console.print(t)
    coded = [f for f in p.fields if f.enum or f.flags or f.other]
    if coded:
        console.print("[bold]Codes[/] (enum: code=name; flags: bit mask=name; "
                      "[red]error[/], [yellow]warning[/], [cyan]info[/])", highlight=False)
        for f in coded:
            console.print(f"  [bold]{f.name}[/]: {_codes(f)}", highlight=False)


_TABLE = {"coil": "co", "discrete": "di", "input": "ir", "holding": "hr"}


@profiles.command("check")
@click.argument("files", nargs=-1, required=True, type=click.Path(path_type=Path))
def check(files: tuple[Path, ...]) -> None:
    """Validate profile files (a directory: its *.yaml); print file:line: field: error for
    each bad one, and file:line: field: warning: for what loads but is doubtful (two
    fields with one title, a title that is only a unit). Each file is checked on its own:
    one that fails never hides another's."""
    bad = 0
    paths = [q for f in files for q in (sorted(f.glob("*.yaml")) if f.is_dir() else [f])]
    for path in paths:
        try:
            if path.exists() and not path.is_file():  # a FIFO would block the reader
                raise ProfileError("not a regular file; not read", file=str(path))
            p = load_profile(path)
        except RtupollError as exc:
            bad += 1
            where = getattr(exc, "file", "")
            parent = f"{path}: the profile it extends does not load: " \
                if where and Path(where) != path else ""
            click.echo(f"{parent}{exc}", err=True)
        else:
            for warning in p.warnings:  # doubtful, not wrong: the profile still loads
                click.echo(warning, err=True)
            n = len(p.warnings)
            click.echo(f"{path}: ok ({p.id}, {len(p.fields)} fields"
                       + (f", {n} warning{'s' if n != 1 else ''}" if n else "") + ")")
    if bad:
        raise ProfileError(f"{bad} of {len(paths)} profile(s) have errors")


def _summary(p: Profile) -> str:
    s, a, lim = p.serial, p.addresses, p.limits
    others = [b for b in s.baudrates if b != s.baudrate]
    lines = [
        f"[bold]{p.id}[/] — {p.vendor} {p.model}" + (f" ({p.kind})" if p.kind else ""),
        f"manual      {p.manual}",
        f"serial      {s.baudrate} {s.bytesize}{s.parity}{s.stopbits}"
        + (f" (can be set to {', '.join(map(str, others))})" if others else "")
        + (", DTR/RTS deasserted (DTR resets the device)" if s.deassert_dtr else ""),
        f"addresses   {a.lo}..{a.hi}, factory {a.default}"
        + (f", answers {a.any} (0x{a.any:02X}) as any device" if a.any else "")
        + "".join(f", {k} (0x{k:02X}) reserved: {v}" for k, v in a.reserved.items()),
        f"requests    {p.addressing.value} addressing, at most {lim.max_registers} registers "
        f"per read, functions {', '.join(f'{f:02d}' for f in sorted(lim.functions))}, "
        f"timeout {lim.timeout:g} s"
        + (", silent on bad requests" if lim.silent_on_error else ""),
        "set-address " + (
            f"{p.set_address.field} via FC{p.set_address.function:02d}" if p.set_address.field
            else f"not supported: {p.set_address.unsupported}"),
    ]
    from rich.markup import escape
    v = p.provenance
    style = "green" if v.level.value == "vendor document" else "yellow" if v.verified \
        else "bold red"
    lines.append(f"verified    [{style}]{v.label}[/]"
                 + ("" if v.verified else ": its values may be wrong"))
    lines += [f"source      {escape(str(d))}" for d in v.sources]
    if v.notes:
        lines.append(f"provenance  {escape(v.notes)}")
    if p.extends:
        lines.append(f"extends     {p.extends}")
    if p.notes:
        lines.append(f"notes       {p.notes}")
    return "\n".join(lines)


_LEVEL_SHORT = {"vendor document": "vendor doc", "two independent implementations": "2 impls",
                "unverified": "UNVERIFIED"}


def level_text(p: Profile, short: bool = True) -> Text:
    """A profile's verification level, coloured: unverified stands out."""
    from rich.text import Text
    v = p.provenance
    text = _LEVEL_SHORT[v.level.value] if short else v.label
    return Text(text, style="green" if v.level.value == "vendor document"
                else "yellow" if v.verified else "bold red")


def _type(f: Field) -> str:
    t = f.layout.type.value
    if t == "string":
        return f"string({2 * f.words})"
    if t in ("u8", "i8"):
        return f"{t} {f.layout.byte}"
    return f"{t} {f.layout.order.value}" if f.words > 1 else t


def _unit(f: Field) -> str:
    parts = [f.unit] if f.unit else []
    if f.layout.scale != 1:
        parts.append(f"raw x {f.layout.scale:g}")
    if f.layout.offset:
        parts.append(f"{f.layout.offset:+g}")
    # scale_by: x a ratio read with it, a line each (the column stays narrow at 80);
    # decode: the documented encoding the stored number is unfolded by
    return "\n".join([" ".join(parts), *(f"x {name}" for name in f.scale_by),
                      *([f"decode {f.transform.value}"] if f.transform else [])]).strip()


def _describe(f: Field) -> str:
    tags = {"default": [], "on_request": ["on request"], "never": ["NEVER polled"]}[f.poll.value]
    tags += ["read alone"] if f.alone else []
    tags += [f"{f.minimum:g}..{f.maximum:g}"] if f.range else []
    tags += [f"variant {f.since}+"] if f.since else []
    tags += ["public source"] if f.source == "public" else []
    tags += ["counter"] if f.counter else []
    if f.interval:
        tags += ["read once at start" if f.interval == float("inf") else
                 f"every {f.interval:g} s"]
    tags += [f"{f.precision} decimals"] if f.precision is not None else []
    tags += [f"{_code(k, f)} = {c.name}" for k, c in f.sentinels.items()]
    # a label (the name people see in Home Assistant and on the dashboard) leads
    text = f"{f.label}: {f.description}" if f.label and f.description else f.label \
        or f.description
    return " ".join([text] + [f"[{t}]" for t in tags]).strip()


def _code(k: int | float, f: Field) -> str:
    """A sentinel as the registers show it (a signed -32768 is 0x8000 on the wire)."""
    if not isinstance(k, int):
        return f"{k:g}"
    if k < 0:
        k += 1 << (f.layout.width or (8 if f.layout.type.value in ("u8", "i8") else 16 * f.words))
    return f"0x{k:X}" if k > 9 else str(k)


_STYLE = {"error": "red", "warning": "yellow", "info": "cyan", "ok": ""}


def _codes(f: Field) -> str:
    def one(key: str, ch: Choice) -> str:
        style = _STYLE[ch.severity.value]
        return f"{key}=[{style}]{ch.name}[/]" if style else f"{key}={ch.name}"

    items = [one(f"0x{m:X}", ch) for m, ch in f.flags.items()] if f.flags else \
        [one(str(c), ch) for c, ch in f.enum.items()]
    if f.other:
        items.append(one("other", f.other))
    return ", ".join(items)
