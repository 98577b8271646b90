"""The wheel a user gets from `pip install .` carries the bundled profiles."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parents[2]


def test_wheel_contains_bundled_profiles_and_entry_point(tmp_path: Path) -> None:
    # the backend [build-system] names, from the test venv ([test] requires it): what
    # `pip install .` runs, without installing it into a new environment every run
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(tmp_path), str(ROOT)], check=True, timeout=300,
                   capture_output=True)
    (wheel,) = tmp_path.glob("rtupoll-*.whl")
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
