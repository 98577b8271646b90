"""The compiled profile cache (``rtupoll.config.compiled``): a command that needs an
unchanged profile takes it from the cache without importing the YAML parser; anything
that could make the cached profile wrong (an edit, a new parent, other code, a broken
cache file) has the file read again, with the usual ``file:line`` errors."""

from __future__ import annotations

import os
import pickle
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from rtupoll.config import compiled
from rtupoll.config.library import load_one, load_profile
from rtupoll.config.paths import PROFILES_ENV, bundled_dir
from rtupoll.config.profile_file import read_profile
from rtupoll.errors import ProfileError
from rtupoll.sim.runner import SimulatedBus
from tests.cli.test_read_imports import imported, loaded

BUNDLED = sorted(p.stem for p in bundled_dir().glob("*.yaml"))
CO2 = "{name: co2, table: input, address: 30009, type: u16, unit: ppm,"


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty cache of the test's own (subprocesses inherit the variable)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(compiled.OFF_ENV, raising=False)
    return tmp_path / "cache" / "rtupoll" / "profiles"


def copy(pid: str, directory: Path) -> Path:
    directory.mkdir(exist_ok=True)
    return Path(shutil.copy(bundled_dir() / f"{pid}.yaml", directory))


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text(encoding="utf-8")
    assert old in text
    path.write_text(text.replace(old, new), encoding="utf-8")


def test_the_second_read_does_not_import_yaml(
        sim: Callable[..., SimulatedBus], cache: Path) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    shutil.rmtree(cache, ignore_errors=True)  # the simulator (this process) may have cached it
    argv = ("read", "--port", bus.port, "--format", "json", "huiwen-aq@1", "co2")
    assert "yaml" in imported(*argv)
    [written] = cache.iterdir()  # one file, no temporary file left
    assert written.name.startswith("huiwen-aq.yaml-") and written.suffix == ".pickle"
    assert not loaded(imported(*argv), "yaml")


@pytest.mark.parametrize("pid", BUNDLED)
def test_a_cached_profile_equals_the_one_read(cache: Path, pid: str) -> None:
    path = bundled_dir() / f"{pid}.yaml"
    first = load_profile(path)
    hit = compiled.load(path)
    assert hit is not None and hit == first == read_profile(path)[0]


def test_an_edit_that_keeps_size_and_mtime_is_seen(tmp_path: Path, cache: Path) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    assert load_profile(path).field("co2").unit == "ppm" and compiled.load(path)
    before = path.stat()
    edit(path, CO2, CO2.replace("ppm", "ppb"))
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
    after = path.stat()
    assert (after.st_size, after.st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    assert load_profile(path).field("co2").unit == "ppb"


def test_an_edit_to_the_parent_is_seen(tmp_path: Path, cache: Path) -> None:
    parent = copy("eastron-sdm120", tmp_path / "mine")
    child = copy("eastron-sdm230", tmp_path / "mine")
    assert load_profile(child).field("voltage").typical == 230.2 and compiled.load(child)
    edit(parent, "typical: 230.2", "typical: 231.2")
    assert load_profile(child).field("voltage").typical == 231.2


@pytest.mark.parametrize("where", ["next to the profile", "on the search path"])
def test_a_new_parent_that_shadows_the_old_one_is_seen(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    child = copy("eastron-sdm230", tmp_path / "mine")
    directory = tmp_path / "mine" if where == "next to the profile" else tmp_path / "more"
    directory.mkdir(exist_ok=True)
    monkeypatch.setenv(PROFILES_ENV, str(tmp_path / "more"))
    assert load_profile(child).field("voltage").typical == 230.2 and compiled.load(child)
    edit(copy("eastron-sdm120", directory), "typical: 230.2", "typical: 231.2")
    assert load_profile(child).field("voltage").typical == 231.2


def test_a_profile_that_became_invalid_gives_the_usual_error(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    assert load_profile(path) and compiled.load(path)
    edit(path, CO2, CO2.replace("unit:", "unti:"))
    with pytest.raises(ProfileError) as cached:
        load_profile(path)
    line = path.read_text(encoding="utf-8").split("unti:")[0].count("\n") + 1
    assert str(cached.value).startswith(f"{path}:{line}: fields[")
    assert str(cached.value).endswith("unti: unknown key (did you mean 'unit'?)")
    monkeypatch.setenv(compiled.OFF_ENV, "1")
    with pytest.raises(ProfileError) as uncached:
        load_profile(path)
    assert str(cached.value) == str(uncached.value)


def test_the_name_as_given_must_still_match_the_id(tmp_path: Path, cache: Path) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    assert load_profile(path) and compiled.load(path)
    link = tmp_path / "mine" / "other.yaml"
    link.symlink_to(path)
    with pytest.raises(ProfileError, match=r"must match the file name 'other\.yaml'"):
        load_profile(link)


def test_another_name_for_the_same_file_is_kept(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    assert load_profile(path).path == str(path)
    monkeypatch.chdir(path.parent)
    hit = compiled.load(Path(path.name))
    assert hit is not None and hit.path == path.name


def test_a_cache_file_loaded_again_is_not_unpickled_again_while_it_is_the_same_file(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    fresh = load_profile(path)  # read, and stored
    assert compiled.load(path) == fresh  # the cache file loaded: this process keeps it
    unpickled: list[bytes] = []
    unpickle = compiled._unpickle
    monkeypatch.setattr(compiled, "_unpickle", lambda data: unpickle(unpickled.append(data)
                                                                      or data))
    assert compiled.load(path) == fresh and unpickled == []
    [file] = cache.iterdir()
    again = file.with_name("again")  # the same bytes in another file (another inode)
    again.write_bytes(file.read_bytes())
    again.replace(file)
    assert compiled.load(path) == fresh and len(unpickled) == 2  # the file, the profile
    assert compiled.load(path) == fresh and len(unpickled) == 2


def test_the_code_stamp_is_that_of_the_code_the_process_started_with(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A process running while rtupoll is upgraded under it neither takes profiles the new
    code cached nor stamps its own as the new code's."""
    code = tmp_path / "profile.py"
    code.write_text("the code", encoding="utf-8")
    monkeypatch.setattr(compiled, "_CODE", (str(code),))
    monkeypatch.setattr(compiled, "_STAMP", None)
    first = compiled._stamp()
    code.write_text("the new code", encoding="utf-8")  # (another size)
    assert compiled._stamp() == first
    monkeypatch.setattr(compiled, "_STAMP", None)  # a process started now
    assert compiled._stamp() != first


class Planted:
    """A pickle that runs a command when it is loaded."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, ...]:
        return os.system, (f"touch {self.marker}",)


def other_stamp(data: bytes, tmp: Path) -> bytes:
    """The file as an rtupoll with another model/profile.py would have written it."""
    stamp, key, chain, payload = pickle.loads(data)
    (module, mtime, size), *rest = stamp
    return pickle.dumps((((module, mtime + 1, size), *rest), key, chain, payload))


def no_sources(data: bytes, tmp: Path) -> bytes:
    stamp, key, _, payload = pickle.loads(data)
    return pickle.dumps((stamp, key, (), payload))


def planted_payload(data: bytes, tmp: Path) -> bytes:
    stamp, key, chain, _ = pickle.loads(data)
    return pickle.dumps((stamp, key, chain, pickle.dumps(Planted(tmp / "ran"))))


DAMAGE: dict[str, Callable[[bytes, Path], bytes]] = {
    "empty": lambda data, tmp: b"",
    "garbage": lambda data, tmp: b"\x80\x05not a pickle at all",
    "truncated": lambda data, tmp: data[: len(data) // 2],
    "foreign": lambda data, tmp: pickle.dumps({"profile": "huiwen-aq"}),
    "another stamp": other_stamp,
    "no sources": no_sources,
    "planted": lambda data, tmp: pickle.dumps(Planted(tmp / "ran")),
    "planted payload": planted_payload,
}


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_broken_cache_file_is_read_past(tmp_path: Path, cache: Path, damage: str) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    fresh = load_profile(path)
    [file] = cache.iterdir()
    file.write_bytes(DAMAGE[damage](file.read_bytes(), tmp_path))
    assert compiled.load(path) is None
    assert load_profile(path) == fresh
    assert compiled.load(path) == fresh  # written again
    assert not (tmp_path / "ran").exists()  # no code ran


def test_a_cache_file_too_large_is_not_read(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = copy("huiwen-aq", tmp_path / "mine")
    assert load_profile(path) and compiled.load(path)
    [file] = cache.iterdir()
    monkeypatch.setattr(compiled, "MAX_BYTES", file.stat().st_size - 1)
    assert compiled.load(path) is None


@pytest.mark.parametrize("variables", [
    {"XDG_CACHE_HOME": "{tmp}/file/cache"},
    {"XDG_CACHE_HOME": "", "HOME": "{tmp}/file/home"},
])
def test_a_cache_that_cannot_be_written_just_reads_the_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, variables: dict[str, str]) -> None:
    (tmp_path / "file").write_text("a file where the cache would go", encoding="utf-8")
    for name, value in variables.items():
        monkeypatch.setenv(name, value.format(tmp=tmp_path))
    for _ in range(2):
        assert load_one("huiwen-aq") == read_profile(bundled_dir() / "huiwen-aq.yaml")[0]
    assert compiled.load(bundled_dir() / "huiwen-aq.yaml") is None


@pytest.mark.parametrize("xdg", ["", "relative/cache"])
def test_without_an_absolute_xdg_cache_home_the_cache_is_in_home(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, xdg: str) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", xdg)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    load_one("huiwen-aq")
    assert [p.name for p in tmp_path.iterdir()] == [".cache"]
    assert compiled.directory() == tmp_path / ".cache" / "rtupoll" / "profiles"
    assert compiled.load(bundled_dir() / "huiwen-aq.yaml") is not None


def test_the_cache_can_be_switched_off(
        sim: Callable[..., SimulatedBus], cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(compiled.OFF_ENV, "1")
    bus = sim("huiwen-aq@1", tick=None)
    argv = ("read", "--port", bus.port, "--format", "json", "huiwen-aq@1", "co2")
    assert "yaml" in imported(*argv)
    assert not cache.exists()  # nothing written
    monkeypatch.delenv(compiled.OFF_ENV)
    load_one("huiwen-aq")  # a warm cache, not used
    monkeypatch.setenv(compiled.OFF_ENV, "1")
    assert compiled.load(bundled_dir() / "huiwen-aq.yaml") is None
    assert "yaml" in imported(*argv)
