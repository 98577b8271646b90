"""The error tree's exit codes are the ones help and the README explain (rtupoll.errors)."""

from __future__ import annotations


def test_the_exit_codes_in_help_and_readme_come_from_the_error_tree() -> None:
    import re
    from pathlib import Path

    from rtupoll.cli import EXIT_CODES
    from rtupoll.errors import RtupollError, exit_codes

    codes = [code for code, _ in exit_codes()]
    owned = {cls.exit_code for cls in _subclasses(RtupollError) if "exit_code" in cls.__dict__}
    assert set(codes) == (owned - {1}) | {0}  # every code a class owns is explained
    assert [int(c) for c in re.findall(r"^  (\d+) ", EXIT_CODES, re.M)] == codes
    readme = (Path(__file__).parents[2] / "README.md").read_text(encoding="utf-8")
    table = readme.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    assert [int(c) for c in re.findall(r"^\| (\d+) \|", table, re.M)] == codes


def _subclasses(cls: type) -> list[type]:
    out = [cls]
    for sub in cls.__subclasses__():
        out += _subclasses(sub)
    return out
