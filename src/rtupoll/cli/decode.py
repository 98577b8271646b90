"""``rtupoll decode``: captured RTU bytes -> frames, and with a profile the fields they carry.

Offline and pure: no port, no pymodbus, no rich (the text output is plain lines, so
it pastes into an issue or a chat as it is). A wrong CRC is the most common finding,
so it is shown with the value it should have had.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import click

from rtupoll.cli.options import format_option, profiles_option
from rtupoll.errors import FrameError, UsageError
from rtupoll.model.carried import Carried, carried_in
from rtupoll.model.profile import Profile
from rtupoll.model.record import finite, nonfinite_text
from rtupoll.numbers import parse_int
from rtupoll.rtu.capture import Frame, decode_stream, parse_hex
from rtupoll.ui.records import json_safe

EPILOG = """\b
Examples:
  rtupoll decode 01 04 00 06 00 02 91 CA 01 04 04 00 00 A0 C1 42 14
  rtupoll decode --profile net-irnet-pro 0104000600 0291CA 010404 0000A0C1 4214
  rtupoll decode --profile huiwen-aq --start 30006 01 04 0A 00 19 00 32 00 FA 13 88 00 00 39 94
  sniffer-dump | rtupoll decode -          (one frame or stream per line)
\b
Bytes may be written 01 04, 0x01,0x04 or 0104; '/' ends a frame when the capture
is known to be split there. Exit code 7 when any frame has a bad CRC.
"""


@click.command(epilog=EPILOG)
@click.argument("hex_bytes", nargs=-1, metavar="HEX...")
@click.option("--profile", "profile_id", metavar="ID",
              help="Decode the fields the frames carry with this profile (an id or a YAML path).")
@click.option("--start", metavar="ADDRESS",
              help="Wire register address of a reply whose request was not captured "
                   "(decimal or 0x hex).")
@profiles_option
@format_option("text", "json")
def decode(hex_bytes: tuple[str, ...], profile_id: str | None, start: str | None,
           profile_dirs: tuple[Path, ...], fmt: str) -> None:
    """Decode captured Modbus RTU frames: CRC, function, addresses, values, exceptions.

    HEX is one frame or a whole stream (frames are split by their structure and CRC);
    '-' or no argument reads lines from standard input. A reply following its request
    is tied to it, so its registers get addresses (and, with --profile, field names).
    """
    if not hex_bytes or hex_bytes == ("-",):
        if sys.stdin.isatty():
            raise UsageError("give the frame as hex arguments, or pipe it in ('-')")
        text: Iterable[str] = (line.replace("/", " / ") + " /" for line in sys.stdin
                               if line.strip())
    else:
        text = hex_bytes
    try:
        chunks = parse_hex(text)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        first = parse_int(start) if start is not None else None
    except ValueError:
        raise UsageError(f"--start {start!r} is not an address (decimal or 0x hex)") from None
    profile = None
    if profile_id:
        from rtupoll.config.library import load_one

        profile = load_one(profile_id, profile_dirs)
    frames = decode_stream(chunks, start=first)
    # with a profile: each frame's fields (a ratio read earlier scales the values after it)
    found = carried_in(frames, profile) if profile else [[] for _ in frames]
    for frame, fields in zip(frames, found, strict=True):
        if fmt == "json":
            click.echo(json.dumps(json_safe(frame_record(frame, fields, profile)),
                                  ensure_ascii=False, allow_nan=False))
        else:
            click.echo("\n".join(describe(frame, fields, profile)))
    bad = [f for f in frames if f.kind != "noise" and not f.crc_ok]
    if bad:
        raise FrameError(f"{len(bad)} of {len(frames)} frame(s) have a bad CRC")


def frame_record(frame: Frame, fields: list[Carried], profile: Profile | None
                 ) -> dict[str, Any]:
    """One frame as a flat JSON object; the keys are documented in docs/scan.md."""
    return {
        "offset": frame.offset,
        "hex": frame.raw.hex(" "),
        "kind": frame.kind,
        "unit": frame.unit,
        "function": frame.function,
        "function_name": frame.function_name,
        "crc_ok": frame.crc_ok,
        "crc": frame.crc_found.hex(" "),
        "crc_expected": frame.crc_expected.hex(" "),
        "table": frame.table.value if frame.table else None,
        "start": frame.start,
        "count": frame.count,
        "values": list(frame.values),
        "exception": frame.exception,
        "notes": list(frame.notes),
        "profile": profile.id if profile else None,
        "fields": [{"field": c.name, "address": c.written, "value": finite(c.value),
                    "unit": c.unit, "raw": list(c.raw), "text": nonfinite_text(c.value) or c.text,
                    "severity": c.severity, "partial": c.partial} for c in fields],
    }


def describe(frame: Frame, fields: list[Carried], profile: Profile | None) -> list[str]:
    """A frame for people: one headline, then what it says, then anything odd about it."""
    head = f"@{frame.offset:<3} {frame.raw.hex(' ').upper()}"
    if frame.kind == "noise":
        return [head, *(f"      {n}" for n in frame.notes)]
    crc = f"CRC {frame.crc_found.hex(' ').upper()} " + (
        "ok" if frame.crc_ok else f"BAD (expected {frame.crc_expected.hex(' ').upper()})")
    lines = [head, f"      {frame.kind} unit {frame.unit}, function {frame.function:#04x} "
                   f"{frame.function_name}; {crc}"]
    if frame.table is not None and frame.start is not None:
        where = _address(frame, frame.start, profile)
        span = f"{frame.count} " if frame.count is not None else ""
        unit = "register(s)" if frame.table.is_register else "bit(s)"
        lines.append(f"      {frame.table.value} {where}, {span}{unit}")
    if frame.values:
        if frame.table is None or frame.table.is_register:
            lines.append("      values " + " ".join(f"{v:04X}" for v in frame.values)
                         + "  (" + " ".join(str(v) for v in frame.values) + ")")
        else:
            lines.append("      values " + " ".join(str(v) for v in frame.values))
    for c in fields:
        if c.partial:
            lines.append(f"      {c.name} ({c.written}): only partly in this frame")
        elif c.value is None and not c.raw:  # a request: the field is asked for
            lines.append(f"      {c.name} ({c.written})")
        else:
            lines.append(f"      {c.name} ({c.written}) = {c.text}"
                         + (f"  [{c.severity}]" if c.severity not in ("", "ok") else ""))
    if profile and frame.table is not None and frame.start is not None and not fields \
            and frame.kind in ("request", "response"):
        lines.append(f"      no {profile.id} field in this range")
    lines += [f"      ! {n}" if _is_problem(n) else f"      {n}" for n in frame.notes
              if not n.startswith("CRC ")]  # the headline already says it
    return lines


def _address(frame: Frame, wire: int, profile: Profile | None) -> str:
    text = f"0x{wire:04X} ({wire})"
    if profile is not None and frame.table is not None and frame.table.is_register:
        written = profile.addressing.show(frame.table, wire)
        if written not in (f"0x{wire:04X}", str(wire)):
            text += f" = {written} in the manual"
    return text


def _is_problem(note: str) -> bool:
    return not note.startswith(("exception ", "a write request", "an echo", "stray"))
