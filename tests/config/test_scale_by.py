"""``scale_by`` at load time: every mistake is one line naming the file, the line of the
field's ``scale_by`` and the field, through ``rtupoll profiles check``; a good one loads
(merge keys and ``extends`` included) and the bundled CHINT profiles use it."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.config.library import load_one, load_profile

HEAD = """\
id: {id}
vendor: ACME
kind: energy meter
model: CT1
manual: CT1 manual
addressing: pdu
fields:
  - {{name: ct, table: holding, address: 6, type: u16{ct}}}
  - {{name: vt, table: holding, address: 7, type: u16, scale: 0.1{vt}}}
  - {{name: mode, table: holding, address: 8, type: u16, enum: {{0: STAR, 1: DELTA}}}}
  - {{name: current, table: holding, address: 16, type: f32, unit: A{cur}}}
  - {{name: power, table: holding, address: 18, type: f32, unit: W{pow}}}
"""


def profile(tmp: Path, *, ct: str = "", vt: str = "", cur: str = "", pow: str = "",
            pid: str = "ct1") -> Path:
    path = tmp / f"{pid}.yaml"
    path.write_text(HEAD.format(id=pid, ct=ct, vt=vt, cur=cur, pow=pow), encoding="utf-8")
    return path


def check(path: Path) -> str:
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 2, (result.stdout + result.stderr)
    return result.stderr.splitlines()[0]


LINE = {"ct": 8, "vt": 9, "current": 11, "power": 12}


@pytest.mark.parametrize(("where", "keys", "message"), [
    ("current", {"cur": ", scale_by: curent"},
     "no field named 'curent' (did you mean 'current'?)"),
    ("current", {"cur": ", scale_by: nothing_like_it"}, "no field named 'nothing_like_it'"),
    ("current", {"cur": ", scale_by: current"}, "current cannot be scaled by itself"),
    ("current", {"cur": ", scale_by: mode"},
     "mode is not a number (enum, flags, string or bool): it cannot scale current"),
    ("current", {"cur": ", scale_by: []"},
     "an empty list; name the field(s) the value is multiplied by"),
    ("current", {"cur": ", scale_by: ct", "ct": ", poll: never"},
     "ct is 'poll: never' (reading it has side effects): it cannot scale current"),
    ("current", {"cur": ", scale_by: ct", "ct": ", interval: 60"},
     "ct has an interval of its own; a factor is read in every cycle that reads current, "
     "so it takes none"),
    ("current", {"cur": ", scale_by: ct", "ct": ", since: 1"},
     "ct is only in variant 1 and later, current in 0 and later: current would have no factor"),
    ("current", {"cur": ", scale_by: ct, access: RW"},
     "current is writable: a write would store the scaled value at the terminals; a scaled "
     "field is read-only"),
    # chains, and so loops, are refused where the scaled factor is used
    ("power", {"pow": ", scale_by: current", "cur": ", scale_by: ct"},
     "current is itself scaled (by ct): a factor is read as stored, so scaled fields cannot "
     "scale others (no chains, no loops)"),
    ("ct", {"ct": ", scale_by: vt", "vt": ", scale_by: ct"},
     "vt is itself scaled (by ct): a factor is read as stored, so scaled fields cannot "
     "scale others (no chains, no loops)"),
])
def test_a_wrong_scale_by_names_file_line_and_field(tmp_path: Path, where: str,
                                                     keys: dict[str, str], message: str
                                                     ) -> None:
    path = profile(tmp_path, **keys)
    index = list(LINE).index(where) if where in ("ct", "vt") else \
        {"current": 3, "power": 4}[where]
    assert check(path) == f"{path}:{LINE[where]}: fields[{index}].scale_by: {message}"


def test_a_factor_named_twice_is_refused_where_it_is(tmp_path: Path) -> None:
    path = profile(tmp_path, cur=", scale_by: [ct, ct]")
    assert check(path) == f"{path}:11: fields[3].scale_by[1]: 'ct' is named twice"


def test_an_enum_field_cannot_be_scaled(tmp_path: Path) -> None:
    path = tmp_path / "ct1.yaml"
    text = HEAD.format(id="ct1", ct="", vt="", cur="", pow="").replace(
        "enum: {0: STAR, 1: DELTA}", "enum: {0: STAR, 1: DELTA}, scale_by: ct")
    path.write_text(text, encoding="utf-8")
    assert check(path) == (f"{path}:10: fields[2].scale_by: mode is not a number (enum, "
                           "flags, string or bool): nothing to multiply")


def test_a_good_profile_loads_with_its_factors(tmp_path: Path) -> None:
    p = load_profile(profile(tmp_path, cur=", scale_by: ct", pow=", scale_by: [ct, vt]"))
    assert p.field("current").scale_by == ("ct",)
    assert p.field("power").scale_by == ("ct", "vt")
    assert p.field("ct").scale_by == ()


def test_a_child_that_drops_a_factor_is_refused_at_the_parents_scale_by(tmp_path: Path
                                                                          ) -> None:
    parent = profile(tmp_path, cur=", scale_by: ct")
    child = tmp_path / "ct1-child.yaml"
    child.write_text("id: ct1-child\nextends: ct1\nwithout: [ct]\n", encoding="utf-8")
    assert check(child) == (f"{child}: the profile it extends does not load: "
                            f"{parent}:11: fields[3].scale_by: no field named 'ct'")


def test_the_chint_profiles_scale_currents_powers_and_energies_by_the_ratios() -> None:
    for pid in ("chint-dtsu666", "chint-dtsu666-e4000"):
        p = load_one(pid)
        assert {f.name: f.scale_by for f in p.fields if f.scale_by} == {
            **{f"voltage_l{n}": ("voltage_ratio",) for n in (1, 2, 3)},
            **{f"current_l{n}": ("current_ratio",) for n in (1, 2, 3)},
            **{name: ("current_ratio", "voltage_ratio") for name in (
                "total_power", "power_l1", "power_l2", "power_l3",
                "import_active_energy", "export_active_energy")},
        }, pid
        # a CT-operated meter is recognised now that its values are scaled
        assert {c.field for c in p.identify}.isdisjoint({"current_ratio", "voltage_ratio"})
