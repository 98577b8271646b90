"""``decode:`` at load time: every mistake is one line naming the file, the line and the
field's key, through ``rtupoll profiles check``; a good one loads, survives the profile
cache, and the bundled Schneider iEM3155 reads its power factor through it."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.config import compiled
from rtupoll.config.library import load_one, load_profile
from rtupoll.model.transforms import Transform

HEAD = """\
id: pf1
vendor: ACME
kind: energy meter
model: PF1
manual: PF1 manual
addressing: pdu
fields:
  - {{name: mode, table: holding, address: 8, type: u16, enum: {{0: STAR, 1: DELTA}}{mode}}}
  - {{name: pf, table: holding, address: 16, type: f32{pf}}}
"""


def profile(tmp: Path, *, mode: str = "", pf: str = "") -> Path:
    path = tmp / "pf1.yaml"
    path.write_text(HEAD.format(mode=mode, pf=pf), encoding="utf-8")
    return path


def check(path: Path) -> str:
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 2, (result.stdout + result.stderr)
    assert "Traceback" not in (result.stdout + result.stderr)
    return result.stderr.splitlines()[0]


@pytest.mark.parametrize(("where", "keys", "message"), [
    ("pf.decode", {"pf": ", decode: four_quadrant"},
     "'four_quadrant' is not one of: four_quadrant_pf"),
    ("mode.decode", {"mode": ", decode: four_quadrant_pf"},
     "four_quadrant_pf decodes a number, and this field is not one (enum, flags, string or "
     "bool)"),
    ("pf.decode", {"pf": ", decode: four_quadrant_pf, access: RW"},
     "a decoded field is read-only (a write would store the value without its encoding)"),
    ("pf.decode", {"pf": ", decode: four_quadrant_pf, range: [0, 2]"},
     "range [0, 2] is outside what four_quadrant_pf gives (-1..1)"),
    ("pf.typical", {"pf": ", decode: four_quadrant_pf, typical: 1.05"},
     "typical 1.05 is outside what four_quadrant_pf gives (-1..1)"),
])
def test_a_wrong_decode_names_file_line_and_key(tmp_path: Path, where: str,
                                                keys: dict[str, str], message: str) -> None:
    path = profile(tmp_path, **keys)
    name, key = where.split(".")
    index, line = {"mode": (0, 8), "pf": (1, 9)}[name]
    assert check(path) == f"{path}:{line}: fields[{index}].{key}: {message}"


def test_a_good_decode_loads_with_the_encodings_range(tmp_path: Path) -> None:
    path = profile(tmp_path, pf=", decode: four_quadrant_pf, range: [-1, 1], typical: 0.95")
    f = load_profile(path).field("pf")
    assert f.transform is Transform.FOUR_QUADRANT_PF and (f.minimum, f.maximum) == (-1, 1)
    narrower = load_profile(profile(tmp_path, pf=", decode: four_quadrant_pf, range: [0, 1]"))
    assert (narrower.field("pf").minimum, narrower.field("pf").maximum) == (0, 1)


def test_a_decoded_field_comes_back_from_the_profile_cache(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("RTUPOLL_NO_PROFILE_CACHE", raising=False)
    path = profile(tmp_path, pf=", decode: four_quadrant_pf")
    first = load_profile(path)
    again = compiled.load(path)  # the transform is one of the model's classes: unpickled
    assert again is not None and again.field("pf").transform is Transform.FOUR_QUADRANT_PF
    assert again == first


def test_the_iem3155_reads_its_power_factor_through_the_vendors_encoding() -> None:
    f = load_one("schneider-iem3155").field("total_power_factor")
    assert f.transform is Transform.FOUR_QUADRANT_PF and f.written == "3084" and not f.writable
    result = rtupoll("profiles", "show", "schneider-iem3155",
                     env={"COLUMNS": "160"})
    assert result.returncode == 0 and "decode four_quadrant_pf" in (result.stdout + result.stderr)
