"""The wheel a user gets from `pip install .` carries the bundled profiles."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parents[2]


# the wheel as `pip install .` has it built: by the backend [build-system] names, through
# its PEP 517 hook, in a process of its own in the project's folder (from the test venv,
# which [test] gives the backend: not installed into a new environment every run, and
# without pip's own start and its metadata step, 2.3 -> 0.6 CPU-s)
BUILD = """
import importlib, sys, tomllib
with open("pyproject.toml", "rb") as f:
    system = tomllib.load(f)["build-system"]
module, _, obj = system["build-backend"].partition(":")
backend = importlib.import_module(module)
for name in filter(None, obj.split(".")):
    backend = getattr(backend, name)
print(backend.build_wheel(sys.argv[1]))
"""


def test_wheel_contains_bundled_profiles_and_entry_point(tmp_path: Path) -> None:
    built = subprocess.run([sys.executable, "-c", BUILD, str(tmp_path)], cwd=ROOT, check=True,
                           timeout=300, capture_output=True, text=True)
    wheel = tmp_path / built.stdout.splitlines()[-1]
    assert wheel.name.startswith("rtupoll-") and wheel.suffix == ".whl", built.stdout
    names = set(zipfile.ZipFile(wheel).namelist())
    for profile in (ROOT / "profiles").glob("*.yaml"):
        assert f"rtupoll/profiles/{profile.name}" in names
    # every module, each package listed in pyproject.toml (rtupoll.app once was not)
    src = ROOT / "src"
    missing = [str(m.relative_to(src)) for m in src.rglob("*.py")
               if str(m.relative_to(src)) not in names]
    assert missing == []
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry).decode()
    assert "rtupoll = rtupoll.cli:main" in text


def test_profiles_list_works_from_any_directory(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "rtupoll", "profiles", "list",
                           "--format", "json"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    ids = {json.loads(line)["id"] for line in proc.stdout.splitlines()}
    assert {"net-irnet-pro", "radar-level", "huiwen-aq", "co2meter-an117",
            "banner-ez-array"} <= ids
