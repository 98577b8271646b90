"""``rtupoll profiles check``: a FIFO is refused without reading it (it hung), each file
of a directory is checked on its own so one broken profile never hides another's
error, and a complex YAML key is named in words, not as ``[ScalarNode(...)]``."""

from __future__ import annotations

import os
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.config.paths import bundled_dir


def profile(directory: Path, pid: str, edit: tuple[str, str] | None = None) -> Path:
    path = directory / f"{pid}.yaml"
    text = (bundled_dir() / "radar-level.yaml").read_text()
    text = text.replace("id: radar-level", f"id: {pid}")
    if edit is not None:
        assert edit[0] in text
        text = text.replace(edit[0], edit[1], 1)
    path.write_text(text)
    return path


def test_a_fifo_is_refused_without_being_read(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    done = rtupoll("profiles", "check", str(fifo))  # it used to hang
    assert done.returncode == 2
    assert done.stderr.splitlines()[0] == f"{fifo}: not a regular file; not read"


def test_every_error_in_a_directory_is_reported_whatever_breaks_first(tmp_path: Path
                                                                       ) -> None:
    broken = profile(tmp_path, "aaa")
    broken.write_text(broken.read_text() + "garbage: [\n")
    wrong = profile(tmp_path, "bbb", ("type: u16", "type: u17"))
    child = tmp_path / "ccc.yaml"
    child.write_text("id: ccc\nextends: aaa\n")
    good = profile(tmp_path, "ddd")
    fifo = tmp_path / "eee.yaml"
    os.mkfifo(fifo)
    result = rtupoll("profiles", "check", str(tmp_path))
    assert result.returncode == 2
    err = result.stderr.splitlines()
    assert err[0].startswith(f"{broken}:") and "YAML syntax" in err[0]
    assert err[1].startswith(f"{wrong}:") and "'u17' is not one of" in err[1]
    assert err[2].startswith(f"{child}: the profile it extends does not load: {broken}:")
    assert err[3] == f"{fifo}: not a regular file; not read"
    assert err[4] == "rtupoll: 4 of 5 profile(s) have errors"
    assert result.stdout.strip() == f"{good}: ok (ddd, 9 fields)"


def test_a_complex_key_is_named_in_words(tmp_path: Path) -> None:
    path = profile(tmp_path, "fff")
    path.write_text(path.read_text() + "? [x, y]\n: 1\n")
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 2
    first = result.stderr.splitlines()[0]
    assert "a key must be a plain name, not a list or a mapping" in first
    assert "ScalarNode" not in result.stderr
    assert first.startswith(f"{path}:")


def test_the_bundled_profiles_check_as_a_directory() -> None:
    result = rtupoll("profiles", "check", str(bundled_dir()))
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert len(result.stdout.splitlines()) == len(list(bundled_dir().glob("*.yaml")))
