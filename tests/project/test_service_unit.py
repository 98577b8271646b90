"""The systemd unit docs/service.md shows is the one measured: ``systemd-analyze security
--offline=true`` (systemd's own rating of a unit's exposure, 0 to 10) reads the block
saved from the page and must rate it at most 3.5, and knows every setting in it."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.project.test_docs_examples import ROOT, blocks

ANALYZE = shutil.which("systemd-analyze")
MOST = 3.5  # "OK" starts below 4; the issue asked for 3.5 or better
SAID = re.compile(r"rates this unit \*\*(\d+\.\d) OK\*\*")


def unit() -> str:
    (block,) = [b for b in blocks(ROOT / "docs" / "service.md")
                if b.note("file") == "rtupoll.service"]
    return block.text + "\n"


@pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed "
                                            "(scripts/setup --test installs systemd)")
def test_the_documented_unit_is_sandboxed_as_the_page_says(tmp_path: Path) -> None:
    path = tmp_path / "rtupoll.service"
    path.write_text(unit())
    assert ANALYZE is not None
    ran = subprocess.run([ANALYZE, "security", "--offline=true", "--no-pager", str(path)],
                         capture_output=True, text=True, timeout=120)
    got = re.search(r"Overall exposure level for rtupoll\.service: (\d+\.\d) (\w+)",
                    ran.stdout)
    assert got is not None, ran.stdout + ran.stderr
    score = float(got.group(1))
    assert score <= MOST, ran.stdout
    # no setting unknown to systemd, none it ignores ("Unknown key name", "ignoring")
    assert not [line for line in ran.stderr.splitlines() if "rtupoll.service" in line], \
        ran.stderr
    said = SAID.search((ROOT / "docs" / "service.md").read_text())
    assert said is not None and float(said.group(1)) == score  # the page says what is


def test_the_unit_keeps_what_rtupoll_needs() -> None:
    """The settings the sandbox must not take away (read without systemd)."""
    text = unit()
    settings: dict[str, list[str]] = {}
    for line in text.splitlines():
        key, sep, value = line.partition("=")
        if sep and not line.startswith(("#", " ")):
            settings.setdefault(key, []).append(value)
    assert settings["Type"] == ["notify"]  # sd_notify: READY=1, WATCHDOG=1
    families = settings["RestrictAddressFamilies"][0].split()
    assert sorted(families) == ["AF_INET", "AF_INET6", "AF_UNIX"]  # AF_UNIX: sd_notify
    assert {"char-ttyUSB rw", "char-ttyACM rw"} <= set(settings["DeviceAllow"])
    assert settings["SupplementaryGroups"] == ["dialout"]
    assert "/var/lib/rtupoll/" in text and settings["StateDirectory"] == ["rtupoll"]
    assert settings["CacheDirectory"] == ["rtupoll"]
    assert settings["Environment"] == ["XDG_CACHE_HOME=%C"]  # the profile cache's home
    assert int(settings["LimitNOFILE"][0]) >= 1024
    assert settings["CapabilityBoundingSet"] == [""]
    assert settings["SystemCallFilter"][0] == "@system-service"
