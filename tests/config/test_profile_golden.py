"""Every library profile against golden data from a source independent of the profile.

Each ``tests/fixtures/golden/ID.yaml`` holds cases taken from somewhere other than the
profile itself: a request/reply printed in the vendor's manual, or register values and
the decoded results from a public implementation's own tests, captures or docs. Each
case names its source. The frames go through the real ``rtupoll decode --profile``
(register values are first put in a read reply, request included, with their CRC), and
what the profile makes of them is compared with what the source says they mean.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from cli_runner import rtupoll

from rtupoll import rtu
from rtupoll.config.library import load_one
from rtupoll.config.paths import bundled_dir
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadRequest

GOLDEN = Path(__file__).parents[1] / "fixtures" / "golden"
LIBRARY = sorted(p.stem for p in bundled_dir().glob("*.yaml"))


def _fixture(pid: str) -> dict[str, Any]:
    # (libyaml's loader where PyYAML has it: every test process reads them all to collect)
    data: dict[str, Any] = yaml.load((GOLDEN / f"{pid}.yaml").read_text(encoding="utf-8"),
                                     Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    return data


def _cases() -> list[Any]:
    out = []
    for path in sorted(GOLDEN.glob("*.yaml")):
        for i, case in enumerate(_fixture(path.stem).get("cases", [])):
            out.append(pytest.param(path.stem, case, id=f"{path.stem}[{i}]"))
    return out


def _stream(case: dict[str, Any]) -> str:
    """The bytes of a case: its frames as printed, or a read of its registers."""
    if "frames" in case:
        return str(case["frames"])
    table = Table(case["table"])
    words = [int(w, 16) for w in str(case["registers"]).split()]
    unit = case.get("unit", 1)
    request = ReadRequest(unit, table.read_function, case["start"], len(words)).frame()
    body = bytes([unit, request[1], 2 * len(words)]) + b"".join(
        w.to_bytes(2, "big") for w in words)
    return (request + rtu.with_crc(body)).hex(" ")


def _decoded(pid: str, stream: str) -> tuple[dict[str, Any], set[str]]:
    """The values the frames carry, and every field they carry or ask for."""
    result = rtupoll("decode", "--profile", pid, "--format", "json", stream)
    assert result.returncode == 0, (result.stdout + result.stderr)
    values: dict[str, Any] = {}
    named: set[str] = set()
    for line in result.stdout.splitlines():
        for f in json.loads(line)["fields"]:
            named.add(f["field"])
            if f["value"] is not None:
                values[f["field"]] = f["text"] if isinstance(f["value"], str) or \
                    (f["text"] and not _is_number(f["text"])) else f["value"]
            elif f["text"] and f["raw"]:  # a sentinel: no value, its name
                values[f["field"]] = f["text"]
    return values, named


def _is_number(text: str) -> bool:
    try:
        float(text.split()[0])
    except (ValueError, IndexError):
        return False
    return True


@pytest.mark.parametrize(("pid", "case"), _cases())
def test_golden_data_decodes_to_what_its_source_says(pid: str, case: dict[str, Any]) -> None:
    assert case.get("source"), "every golden case names its source"
    got, named = _decoded(pid, _stream(case))
    for name in case.get("asks", []):  # a request: the fields the source says it reads
        assert name in named, f"{pid}: the frame does not ask for {name} ({sorted(named)})"
    for name, want in case.get("expect", {}).items():
        assert name in got, f"{pid}: the golden data holds no {name} ({sorted(got)})"
        value = got[name]
        if isinstance(want, float) or isinstance(value, float):
            tol = case.get("tolerance", 1e-6)
            assert math.isclose(float(value), float(want), rel_tol=tol, abs_tol=tol), \
                f"{pid}.{name}: {value} != {want} ({case['source']})"
        else:
            assert value == want, f"{pid}.{name}: {value!r} != {want!r} ({case['source']})"


@pytest.mark.parametrize("pid", LIBRARY)
def test_every_library_profile_has_golden_data_with_a_source(pid: str) -> None:
    path = GOLDEN / f"{pid}.yaml"
    assert path.is_file(), f"{pid} has no golden data ({path})"
    data = _fixture(pid)
    assert data["profile"] == pid
    if not data.get("cases"):  # allowed only with the reason written down (docs/profiles.md)
        assert data.get("missing"), f"{pid}: no cases and no reason why"
    for case in data.get("cases", []):
        assert case.get("source") and (case.get("expect") or case.get("asks"))


@pytest.mark.parametrize("pid", LIBRARY)
def test_every_library_profile_names_its_documents(pid: str) -> None:
    p = load_one(pid)
    assert p.provenance.given, f"{pid} has no provenance"
    if p.provenance.verified:
        assert p.provenance.sources


def test_the_docs_list_every_profiles_level_as_its_file_says() -> None:
    text = (Path(__file__).parents[2] / "docs" / "profiles.md").read_text(encoding="utf-8")
    section = text.split("### Verification level of every bundled profile", 1)[1]
    section = section.split("\n#", 1)[0]
    rows = dict(re.findall(r"^\| `([a-z0-9-]+)` \| ([a-z ]+) \|", section, re.M))
    assert set(rows) == set(LIBRARY)
    for pid, level in rows.items():
        assert load_one(pid).provenance.level.value == level, pid
