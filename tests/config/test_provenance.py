"""Provenance: where a profile's facts come from, how far they are verified, and what
rtupoll says about it (profiles list/show, scan, a warning when an unverified one is used)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.model.profile import Verification
from rtupoll.sim.runner import simulated_bus

FIXTURES = Path(__file__).parents[1] / "fixtures" / "profiles"

GOOD = """\
id: mine
vendor: ACME
model: TH1
manual: TH1 sheet
provenance:
  level: {level}
  sources:
{sources}
addressing: pdu
fields:
  - {{name: t, table: input, address: 0, type: i16}}
"""
ONE = "    - {title: TH1 Modbus manual, version: rev 3, where: https://example.com/th1.pdf}\n"


def _check(tmp_path: Path, text: str) -> tuple[int, str]:
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    result = rtupoll("profiles", "check", str(path))
    return result.returncode, result.stderr.splitlines()[0] if result.stderr else ""


@pytest.mark.parametrize(("level", "sources", "line", "message"), [
    ("guessed", ONE, 6, "provenance.level: 'guessed' is not one of: vendor document, "
                        "two independent implementations, unverified"),
    ("vendor document", "    []\n", 8, "provenance.sources: a profile verified by 'vendor "
                                       "document' names its sources (title, where)"),
    ("two independent implementations", ONE, 8,
     "provenance.sources: 'two independent implementations' names two sources, not 1"),
    ("vendor document", "    - {title: TH1 manual}\n", 8,
     "provenance.sources[0]: missing required key 'where'"),
    ("vendor document", "    - {title: TH1, where: x, page: 4}\n", 8,
     "provenance.sources[0].page: unknown key"),
])
def test_bad_provenance_is_named_by_file_line_and_field(tmp_path: Path, level: str,
                                                        sources: str, line: int,
                                                        message: str) -> None:
    code, first = _check(tmp_path, GOOD.format(level=level, sources=sources))
    assert code == 2
    assert first.startswith(f"{tmp_path}/mine.yaml:{line}: ") and message in first, first


def test_good_provenance_is_shown_by_show_and_list(tmp_path: Path) -> None:
    (tmp_path / "mine.yaml").write_text(GOOD.format(level="vendor document", sources=ONE))
    code, _ = _check(tmp_path, GOOD.format(level="vendor document", sources=ONE))
    assert code == 0
    show = rtupoll("profiles", "show", "mine", "--profiles", str(tmp_path),
                   env={"COLUMNS": "200"})
    assert "verified    vendor document" in show.stdout
    assert "source      TH1 Modbus manual (rev 3) <https://example.com/th1.pdf>" in show.stdout
    listed = rtupoll("profiles", "list", "--format", "json",
                     "--profiles", str(tmp_path))
    recs = {r["id"]: r for r in map(json.loads, listed.stdout.splitlines())}
    assert recs["mine"]["verification"] == "vendor document"
    assert recs["mine"]["sources"] == ["TH1 Modbus manual (rev 3) <https://example.com/th1.pdf>"]
    assert recs["md02"]["verification"] == "unverified"


def test_a_profile_without_provenance_is_shown_as_unverified(tmp_path: Path) -> None:
    text = GOOD.format(level="unverified", sources="").replace(
        "provenance:\n  level: unverified\n  sources:\n", "")
    (tmp_path / "mine.yaml").write_text(text)
    show = rtupoll("profiles", "show", "mine", "--profiles", str(tmp_path),
                   env={"COLUMNS": "200"})
    assert "verified    unverified (no provenance): its values may be wrong" in show.stdout


def test_list_table_shows_each_level() -> None:
    out = rtupoll("profiles", "list", env={"COLUMNS": "200"}).stdout
    rows = {line.split()[0]: line for line in out.splitlines()
            if line.startswith("   ") and line.strip()}
    assert rows["eastron-sdm630"].rstrip().endswith("vendor doc")
    assert rows["schneider-iem3155"].rstrip().endswith("2 impls")
    assert rows["md02"].rstrip().endswith("UNVERIFIED")


def test_using_an_unverified_profile_warns_once_in_one_line() -> None:
    assert load_one("md02").provenance.level is Verification.UNVERIFIED
    with simulated_bus(["md02@1", "md02@3", "eastron-sdm630@2"],
                       tcp=True, tick=None) as bus:
        proc = rtupoll("poll", "--port", bus.port, "--once", "--format", "json",
                       "md02@1", "md02@3")
        verified = rtupoll("read", "--port", bus.port, "--format", "json",
                           "eastron-sdm630@2", "voltage_l1")
    assert proc.returncode == 0, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if "md02" in line]
    assert len(warnings) == 1
    assert "profile md02 is unverified" in warnings[0]
    assert verified.returncode == 0, verified.stderr
    assert "unverified" not in verified.stderr


def test_scan_shows_the_level_of_the_profile_it_found() -> None:
    with simulated_bus(["eastron-sdm630@2"], tcp=True, tick=None) as bus:
        result = rtupoll("scan", "--port", bus.port, "--baudrate", "9600",
                         "--addresses", "2", "--format", "json")
    assert result.returncode == 0, (result.stdout + result.stderr)
    rec = json.loads(result.stdout.splitlines()[0])
    assert rec["profile"] == "eastron-sdm630" and rec["verification"] == "vendor document"
