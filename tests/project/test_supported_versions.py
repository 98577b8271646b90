"""What pyproject.toml promises about versions is what the test command runs.

scripts/test runs the suite on the oldest and the newest supported Python the machine
has, and once more with the lowest allowed version of every runtime dependency
(scripts/minimum-versions.txt). These checks keep the declarations, the tools' settings,
the README and that file in step, so a range can't widen without being run.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

ROOT = Path(__file__).parents[2]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
MINIMUMS = ROOT / "scripts" / "minimum-versions.txt"


def supported() -> list[str]:
    """The Python versions the classifiers name, oldest first ("3.11", ...)."""
    found = [c.rsplit(" :: ", 1)[1] for c in PROJECT["project"]["classifiers"]
             if re.fullmatch(r"Programming Language :: Python :: 3\.\d+", c)]
    return sorted(found, key=lambda v: int(v.split(".")[1]))


def runtime_requirements() -> list[Requirement]:
    """The dependencies a user installs: the core ones and the edge features' extras."""
    extras = PROJECT["project"]["optional-dependencies"]
    reqs = [Requirement(r) for r in PROJECT["project"]["dependencies"]]
    reqs += [Requirement(r) for name in ("mqtt", "metrics") for r in extras[name]]
    return reqs


def pins() -> dict[str, str]:
    out = {}
    for line in MINIMUMS.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            out[name.strip().lower().replace("_", "-")] = version.strip()
    return out


def test_the_supported_pythons_are_one_range_from_requires_python() -> None:
    versions = supported()
    assert versions, "no Python classifiers"
    minors = [int(v.split(".")[1]) for v in versions]
    assert minors == list(range(minors[0], minors[-1] + 1)), versions  # no gap
    assert PROJECT["project"]["requires-python"] == f">={versions[0]}"
    assert PROJECT["tool"]["mypy"]["python_version"] == versions[0]
    assert PROJECT["tool"]["ruff"]["target-version"] == "py" + versions[0].replace(".", "")


def test_the_readme_names_the_supported_pythons() -> None:
    versions = supported()
    said = ", ".join(versions[:-1]) + f" or {versions[-1]}"
    assert f"Python {said}" in (ROOT / "README.md").read_text()


def test_every_runtime_dependency_has_a_lower_and_an_upper_bound() -> None:
    for req in runtime_requirements():
        ops = {s.operator for s in req.specifier}
        assert ">=" in ops and "<" in ops, f"{req}: needs a lower and an upper bound"


def test_the_minimum_versions_are_the_lowest_the_ranges_allow() -> None:
    pinned = pins()
    for req in runtime_requirements():
        name = req.name.lower().replace("_", "-")
        assert name in pinned, f"{req.name} is not in {MINIMUMS.name}"
        assert pinned[name] in req.specifier, (req, pinned[name])
        low = next(s.version for s in req.specifier if s.operator == ">=")
        assert SpecifierSet(f"=={low}").contains(pinned[name]), (req, pinned[name])
