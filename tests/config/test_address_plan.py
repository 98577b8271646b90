"""Address plan files: CSV and YAML read the same; a bad plan is refused with file and line
(rtupoll.config.address_plan)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.address_plan import load_plan
from rtupoll.errors import ConfigError, RefusedError

FIXTURES = Path(__file__).parents[1] / "fixtures" / "commission"


def test_csv_and_yaml_plans_read_the_same() -> None:
    csv_plan = load_plan(FIXTURES / "three.csv")
    yaml_plan = load_plan(FIXTURES / "three.yaml")
    assert [(c.profile.id, c.old, c.new, c.check) for c in csv_plan] == \
        [(c.profile.id, c.old, c.new, c.check) for c in yaml_plan] == [
            ("radar-level", 1, 11, None),
            ("huiwen-aq", 2, 12, ("co2_failure", "NO_FAULT")),
            ("banner-ez-array", 3, 13, None)]
    assert csv_plan[1].where.endswith("three.csv:4")


@pytest.mark.parametrize(("name", "message", "code"), [
    ("bad-column.csv", "bad-column.csv:1: unknown column 'adress'", 2),
    ("twice.csv", "twice.csv:3: address 11 is given twice", 2),
    ("reserved.csv", "reserved.csv:3: radar-level@2 -> 0: 0 is the broadcast address", 8),
    ("unsupported.yaml", "unsupported.yaml:1: net-irnet-pro cannot be readdressed", 8),
])
def test_a_bad_plan_is_refused_with_file_and_line_before_anything_runs(
        name: str, message: str, code: int) -> None:
    with pytest.raises((ConfigError, RefusedError)) as info:
        load_plan(FIXTURES / name)
    assert message in str(info.value)
    assert info.value.exit_code == code
