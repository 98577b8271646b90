"""Commissioning plan files: the rows of ``rtupoll set-address --plan FILE``.

A plan is written by a person in a spreadsheet or an editor, so both CSV and YAML
are accepted, and every mistake is reported as ``file:line: message`` before the
first row runs: a plan that stops half-way because row 12 has a typo is exactly
what a plan is meant to prevent.

CSV (header required; ``#`` lines are comments)::

    profile,address,new,check
    radar-level,1,11,
    huiwen-aq,1,12,slave_address=1

YAML (a list, or a mapping with ``changes:``)::

    - {profile: radar-level, address: 1, new: 11}
    - {profile: huiwen-aq, address: 1, new: 12, check: "serial_number=A1234"}
"""

from __future__ import annotations

import csv
import dataclasses
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path

from rtupoll.config.library import load_one
from rtupoll.errors import ConfigError, RefusedError, RtupollError
from rtupoll.model.addressing import Change, refuse
from rtupoll.model.profile import Profile
from rtupoll.numbers import parse_unit

COLUMNS = {"profile": "profile", "address": "address", "old": "address", "current": "address",
           "new": "new", "new_address": "new", "check": "check", "identity": "check"}


def load_plan(path: Path, profile_dirs: Iterable[Path] = (),
              avoid: Mapping[int, str] | None = None) -> list[Change]:
    """Read and check a plan; every row is refused or accepted before anything is sent."""
    cache: dict[str, Profile] = {}
    dirs = tuple(profile_dirs)

    def profile(pid: str) -> Profile:
        if pid not in cache:
            cache[pid] = load_one(pid, dirs)
        return cache[pid]

    rows = _yaml_rows(path) if path.suffix.lower() in (".yaml", ".yml") else _csv_rows(path)
    changes = []
    for line, row in rows:
        where = f"{path}:{line}"
        try:
            change = Change(profile(row["profile"]), _address(row["address"], "address"),
                            _address(row["new"], "new"), _check(row.get("check", "")), where,
                            avoid or {})
            refuse(change)
        except RefusedError as exc:  # refused stays refused (exit 8), with the row's place
            raise RefusedError(f"{where}: {exc}") from None
        except RtupollError as exc:
            raise ConfigError(str(exc), file=str(path), line=line) from None
        changes.append(change)
    if not changes:
        raise ConfigError("the plan has no rows", file=str(path), line=1)
    _no_clashes(path, changes)
    olds = Counter(c.old for c in changes)
    return [dataclasses.replace(c, shared=True) if olds[c.old] > 1 else c for c in changes]


def _csv_rows(path: Path) -> list[tuple[int, dict[str, str]]]:
    from rtupoll.config.yamlsrc import read_bytes, utf8

    text = utf8(read_bytes(path, ConfigError), str(path), ConfigError)
    lines = [(n, t.rstrip("\r")) for n, t in enumerate(text.split("\n"), 1)
             if t.strip() and not t.lstrip().startswith("#")]
    if not lines:
        raise ConfigError("the plan is empty", file=str(path), line=1)
    bad = next(((n, t) for n, t in lines if not t.replace("\t", " ").isprintable()), None)
    if bad:
        raise ConfigError("a control character (a CSV file is text)", file=str(path),
                          line=bad[0])
    try:
        return _csv_table(path, lines)
    except csv.Error as exc:
        raise ConfigError(f"CSV: {exc}", file=str(path), line=lines[0][0]) from None


def _csv_table(path: Path, lines: list[tuple[int, str]]) -> list[tuple[int, dict[str, str]]]:
    reader = csv.reader([t for _, t in lines], skipinitialspace=True)
    header = [h.strip().lower() for h in next(reader)]
    unknown = [h for h in header if h not in COLUMNS]
    if unknown:
        raise ConfigError(f"unknown column {unknown[0]!r} (columns: profile, address, new, "
                          "check)", file=str(path), line=lines[0][0])
    keys = [COLUMNS[h] for h in header]
    for need in ("profile", "address", "new"):
        if need not in keys:
            raise ConfigError(f"missing column {need!r} (header: profile,address,new[,check])",
                              file=str(path), line=lines[0][0])
    out = []
    for (line, _), cells in zip(lines[1:], reader, strict=False):
        if len(cells) > len(keys):
            raise ConfigError(f"{len(cells)} cells, the header has {len(keys)}", file=str(path),
                              line=line)
        row = {k: c.strip() for k, c in zip(keys, cells, strict=False)}
        missing = [k for k in ("profile", "address", "new") if not row.get(k)]
        if missing:
            raise ConfigError(f"missing {missing[0]!r}", file=str(path), line=line)
        out.append((line, row))
    return out


def _yaml_rows(path: Path) -> list[tuple[int, dict[str, str]]]:
    from rtupoll.config.yamlsrc import load

    root = load(path, ConfigError)
    node = root.mapping({"changes"}, {"changes"})["changes"] if root.is_mapping else root
    out = []
    for item in node.sequence():
        m = item.mapping({"profile", "address", "new", "check"}, {"profile", "address", "new"})
        out.append((item.line, {k: v.text() for k, v in m.items()}))
    return out


def _address(text: str, what: str) -> int:
    try:
        return parse_unit(text)
    except ValueError as exc:
        raise ConfigError(f"{what}: {exc}") from None


def _check(text: str) -> tuple[str, str] | None:
    if not text.strip():
        return None
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise ConfigError(f"check {text!r} is not FIELD=VALUE (e.g. serial_number=A1234)")
    return name.strip(), value.strip()


def _no_clashes(path: Path, changes: list[Change]) -> None:
    """Two rows giving out one address would leave two devices on it."""
    seen: dict[int, str] = {}
    for c in changes:
        if c.new in seen:
            raise ConfigError(f"address {c.new} is given twice (also at {seen[c.new]})",
                              file=str(path), line=int(c.where.rsplit(":", 1)[1]))
        seen[c.new] = c.where


