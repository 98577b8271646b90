"""`rtupoll profiles check` names the file, line and field of every mistake."""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_runner import rtupoll
from forked_cli import rtupoll_run

FIXTURES = Path(__file__).parents[1] / "fixtures" / "profiles"

EXPECTED = {
    "bad-order": "6: byte_order: 'BACD' is not one of: ABCD, BADC, CDAB, DCBA",
    "duplicate-name": "8: fields[1].name: duplicate field name 'co2' (first at line 7)",
    "enum-fit": "14: fields[0].enum.300: code 300 does not fit the field (0..255)",
    "flags-float": "12: fields[0].flags: enum and flags need an integer type, not f32",
    "id-mismatch": "1: id: id 'some-other-id' must match the file name 'id-mismatch.yaml'",
    "missing-key": "7: fields[0]: missing required key 'type'",
    "modicon-range": "8: fields[1].address: 30001 is not a holding register reference "
                     "(40001..49999)",
    "overlap": "8: fields[1].address: concentration overlaps temperature (line 7) in the input "
               "table",
    "range-fit": "7: fields[0].range: [0, 7000] does not fit u16 with this scale and offset "
                 "(0..6553.5)",
    "set-address-fc": "10: set_address.function: the device does not support function 6 "
                      "(limits.functions)",
    "syntax": "8: YAML syntax: did not find expected ',' or '}'",
    "too-wide": "9: fields[0].type: 4 registers are more than the device reads at once (2)",
    "values-fit": "13: fields[0].values[2]: 9000000 does not fit the field: 90000 is outside "
                  "u16 (0..65535)",
    "unknown-key": "7: fields[0].unti: unknown key (did you mean 'unit'?)",
    "writable-input": "7: fields[0].access: input registers cannot be written",
    "wrong-type": "10: fields[0].type: 'float32' is not one of: u16, i16, u32, i32, u64, i64, "
                  "f32, f64, u8, i8, string, bool",
}


def test_every_fixture_has_an_expectation() -> None:
    assert {p.stem for p in FIXTURES.glob("*.yaml")} == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_check_reports_file_line_and_field(name: str) -> None:
    path = FIXTURES / f"{name}.yaml"
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode != 0
    first = result.stderr.splitlines()[0]
    assert first == f"{path}:{EXPECTED[name]}"
    assert "Traceback" not in (result.stdout + result.stderr)


def test_check_passes_good_profiles_and_counts_bad_ones() -> None:
    bundled = sorted(Path(__file__).parents[2].joinpath("profiles").glob("*.yaml"))
    bad = FIXTURES / "overlap.yaml"
    result = rtupoll("profiles", "check", *map(str, bundled), str(bad))
    assert result.stdout.count(": ok (") == len(bundled) >= 20
    assert f"1 of {len(bundled) + 1} profile(s) have errors" in result.stderr


def test_check_exit_code_through_main(tmp_path: Path) -> None:
    import sys

    bad = tmp_path / "x.yaml"
    bad.write_text("id: x\n")
    proc = rtupoll_run([sys.executable, "-m", "rtupoll", "profiles", "check", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.splitlines()[0] == f"{bad}:1: missing required key 'addressing'"
    assert "Traceback" not in proc.stderr


def test_bad_user_profile_directory_fails_listing_with_its_error(tmp_path: Path) -> None:
    (tmp_path / "mine.yaml").write_text((FIXTURES / "unknown-key.yaml").read_text()
                                        .replace("id: unknown-key", "id: mine"))
    result = rtupoll("profiles", "list", "--profiles", str(tmp_path))
    assert result.returncode == 2
    assert result.stderr == f"rtupoll: {tmp_path}/mine.yaml:7: fields[0].unti: unknown key " \
                            "(did you mean 'unit'?)\n"


@pytest.mark.parametrize("columns", ["80", "140"])
def test_show_prints_wire_and_manual_addresses_flags_and_codes(columns: str) -> None:
    result = rtupoll("profiles", "show", "banner-ez-array",
                     env={"COLUMNS": columns})
    assert result.returncode == 0
    out = result.stdout
    words = " ".join(out.split())  # descriptions may wrap
    assert "hr 40001 = 0x9C41" in out and "ir 30521 = 0x7739" in out  # never cut
    assert "[NEVER polled]" in words and "[on request]" in words
    assert "set-address slave_address via FC16" in out
    assert "measurement_1_mode: 0=DISABLED, 1=FBB" in words
    assert max(len(line) for line in out.splitlines()) <= int(columns)
