"""A field's title (``label:``, else its description up to the first aside): distinct in
its profile and more than a unit. Every bundled profile keeps to it; a ``label:`` that
breaks it is an error at its line; a user's profile whose descriptions break it loads,
and ``profiles check`` warns at the description's line."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.config.paths import bundled_dir
from rtupoll.config.profile_file import read_profile
from rtupoll.errors import ProfileError

BUNDLED = sorted(bundled_dir().glob("*.yaml"))

HEAD = """\
id: {pid}
vendor: Test
model: Meter
manual: none
addressing: pdu
fields:
"""


def write(tmp_path: Path, fields: str, pid: str = "meter") -> Path:
    path = tmp_path / f"{pid}.yaml"
    path.write_text(HEAD.format(pid=pid) + fields)
    return path


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.stem)
def test_every_bundled_title_is_distinct_and_more_than_a_unit(path: Path) -> None:
    profile, _ = read_profile(path)
    assert profile.warnings == ()
    titles = [f.title.casefold().replace(" ", "") for f in profile.fields]
    assert len(set(titles)) == len(titles)
    units = {f.unit.casefold().replace(" ", "") for f in profile.fields if f.unit}
    assert not units & set(titles)
    assert max(len(f.title) for f in profile.fields) <= 40


def test_the_labels_the_issue_named() -> None:
    em24, _ = read_profile(bundled_dir() / "carlo-gavazzi-em24.yaml")
    titles = {f.name: f.title for f in em24.fields}
    assert titles["import_active_energy"] == "Import energy total"
    assert titles["export_active_energy"] == "Export energy total"
    assert titles["import_energy_l2"] == "Import energy L2"
    radar, _ = read_profile(bundled_dir() / "radar-level.yaml")
    assert [f.title for f in radar.fields[:4]] == [
        "Distance to water (cm)", "Distance to water (mm)", "Water level (cm)",
        "Water level (mm)"]
    irnet, _ = read_profile(bundled_dir() / "net-irnet-pro.yaml")
    assert irnet.field("full_scale").title == "Full scale"
    # without a label, the description up to its first aside, else the name in words
    assert irnet.field("concentration").title == "Target gas concentration"
    assert irnet.field("measurement_unit").title == "Measurement unit"


WHY = ": a label says what the field measures, and tells it from the profile's other fields"
A = "  - {name: a, table: input, address: 0, type: u16, unit: kWh, "
B = "  - {name: b, table: input, address: 1, type: u16, unit: kWh, "


@pytest.mark.parametrize(("fields", "line", "message"), [
    (A + "label: ''}\n", 7, "fields[0].label: an empty label"),
    (A + "label: '  Energy'}\n", 7, "fields[0].label: '  Energy': a label is one line, with no "
                                    "spaces at its ends"),
    (A + "label: \"Energy\\nimported\"}\n", 7, "fields[0].label: 'Energy\\nimported': a label "
                                               "is one line, with no spaces at its ends"),
    (A + f"label: {'x' * 41}}}\n", 7, "fields[0].label: 41 characters; a label has at most 40"),
    (A + "label: [Energy]}\n", 7, "fields[0].label: expected text, got a list"),
    (A + "label: K W h}\n", 7, "fields[0].label: 'K W h' is only a unit" + WHY),
    (A + "description: Energy imported}\n" + B + "label: energy  IMPORTED}\n", 8,
     "fields[1].label: 'energy  IMPORTED' is the title of a (line 7) too" + WHY),
    (A + "label: Energy}\n" + B + "description: Energy (resettable)}\n", 7,
     "fields[0].label: 'Energy' is the title of b (line 8) too" + WHY),
    (A + "label: Energy}\n" + B + "label: Energy}\n", 8,
     "fields[1].label: 'Energy' is the title of a (line 7) too" + WHY),
])
def test_a_label_that_breaks_the_rules_is_an_error_at_its_line(
        tmp_path: Path, fields: str, line: int, message: str) -> None:
    path = write(tmp_path, fields)
    with pytest.raises(ProfileError) as exc:
        read_profile(path)
    assert str(exc.value) == f"{path}:{line}: {message}"
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 2
    assert result.stderr.splitlines()[0] == f"{path}:{line}: {message}"


def test_a_user_profile_with_doubtful_titles_loads_and_check_warns(tmp_path: Path) -> None:
    path = write(tmp_path, A + "description: kWh (+) total}\n"
                 + B + "description: kWh (-) total}\n"
                 + "  - {name: c, table: input, address: 2, type: u16, unit: cm,\n"
                 + "     description: Water level}\n"
                 + "  - {name: d, table: input, address: 3, type: u16, unit: mm,\n"
                 + "     description: Water level}\n"
                 + "  - {name: e, table: input, address: 4, type: u16, unit: mm,\n"
                 + f"     description: {'Distance ' * 5}}}\n"
                 + "  - {name: f, table: input, address: 5, type: u16, unit: mm,\n"
                 + "     label: Water level (mm), description: Water level}\n")
    profile, _ = read_profile(path)
    assert [f.title for f in profile.fields][:2] == ["KWh", "KWh"]
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert result.stdout == f"{path}: ok (meter, 6 fields, 4 warnings)\n"
    assert result.stderr.splitlines() == [
        f"{path}:7: fields[0].description: warning: a is titled 'KWh', only a unit; "
        "give it a 'label:'",
        f"{path}:8: fields[1].description: warning: b is titled 'KWh', the title of a "
        "(line 7) too; give it a 'label:'",
        f"{path}:12: fields[3].description: warning: d is titled 'Water level', the title of c "
        "(line 9) too; give it a 'label:'",
        f"{path}:14: fields[4].description: warning: e is titled '{'Distance ' * 4}Distance', "
        "44 characters (at most 40); give it a 'label:'"]


def test_a_child_profile_labels_a_parent_field_and_is_checked_with_it(tmp_path: Path) -> None:
    write(tmp_path, A + "description: Energy}\n" + B + "description: Power}\n", pid="base")
    child = tmp_path / "child.yaml"
    child.write_text("id: child\nextends: base\nfields:\n"
                     "  - {name: b, table: input, address: 1, type: u16, label: Energy}\n")
    with pytest.raises(ProfileError) as exc:
        read_profile(child)
    assert str(exc.value) == f"{child}:4: fields[0].label: 'Energy' is the title of a " \
                             "(base.yaml:7) too" + WHY
    child.write_text(child.read_text().replace("label: Energy", "label: Energy exported"))
    assert [f.title for f in read_profile(child)[0].fields] == ["Energy", "Energy exported"]
