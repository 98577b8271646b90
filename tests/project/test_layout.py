"""tests/ mirrors src/rtupoll/ (tests/README.md): every layer has its folder of tests,
every test file is in a layer's folder (or cli/, project/, windows/), and no two test files share
a name (pytest's default import mode, which the suite uses, needs that)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

TESTS = Path(__file__).parents[1]
SOURCE = TESTS.parent / "src" / "rtupoll"
# folders that are not a package of src/rtupoll: the commands, the project as a whole,
# the Windows build under Wine, and the shared data
OWN = {"cli", "project", "windows", "fixtures"}


def layers() -> set[str]:
    return {p.parent.name for p in SOURCE.glob("*/__init__.py")}


def test_every_layer_has_its_folder_of_tests() -> None:
    missing = {layer for layer in layers() if not list((TESTS / layer).glob("test_*.py"))}
    assert not missing, f"layers with no tests/<layer>/test_*.py: {sorted(missing)}"


def test_every_test_file_is_in_a_layer_folder() -> None:
    allowed = layers() | OWN
    astray = [
        str(p.relative_to(TESTS))
        for p in TESTS.rglob("test_*.py")
        if "fixtures" not in p.relative_to(TESTS).parts
        and (len(p.relative_to(TESTS).parts) != 2 or p.parent.name not in allowed)
    ]
    assert not astray, f"test files outside tests/<layer>/: {astray}"
    folders = {p.name for p in TESTS.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))}
    assert folders <= allowed, f"folders that mirror nothing: {sorted(folders - allowed)}"


def test_test_file_names_are_unique() -> None:
    names = Counter(p.name for p in TESTS.rglob("test_*.py") if "fixtures" not in p.parts)
    assert not [n for n, k in names.items() if k > 1], names.most_common(3)


def test_no_package_markers_that_shadow_a_module() -> None:
    # tests/io/__init__.py would make ``import io`` find the tests' folder
    assert not list(TESTS.glob("*/__init__.py"))
