"""The compiled profile cache trusts only the user's own files: a forged entry (another
unit: as easily a wrong scale, a value reported ``ok``) in a directory or file another user
owns, or that others may write, is never used and nothing is stored there; the profile
file is read."""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
from pathlib import Path

import pytest

from rtupoll.config import compiled
from rtupoll.config.library import load_profile
from rtupoll.config.paths import bundled_dir
from rtupoll.config.profile_file import read_profile
from rtupoll.model.profile import Profile

OTHER_UID = 4242


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(compiled.OFF_ENV, raising=False)
    return tmp_path / "cache" / "rtupoll" / "profiles"


def forge(file: Path) -> None:
    """What someone who can write the cache file would plant: co2 in another unit."""
    stamp, key, chain, payload = pickle.loads(file.read_bytes())
    real: Profile = pickle.loads(payload)
    fields = tuple(dataclasses.replace(f, unit="forged") if f.name == "co2" else f
                   for f in real.fields)
    forged = dataclasses.replace(real, fields=fields)
    file.write_bytes(pickle.dumps((stamp, key, chain, pickle.dumps(forged))))


def not_mine(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``path`` owned by another user (as root: chown; otherwise this process becomes
    someone else as far as the cache can tell)."""
    if os.getuid() == 0:
        os.chown(path, OTHER_UID, -1)
    else:
        uid = os.getuid()
        monkeypatch.setattr(os, "getuid", lambda: uid + 1)


def setup(tmp_path: Path, cache: Path) -> tuple[Path, Profile, Path]:
    path = Path(shutil.copy(bundled_dir() / "huiwen-aq.yaml", tmp_path))
    real = load_profile(path)
    [file] = cache.iterdir()
    forge(file)
    return path, real, file


def test_a_forged_entry_in_the_users_own_cache_is_what_the_check_is_about(
        tmp_path: Path, cache: Path) -> None:
    path, real, _ = setup(tmp_path, cache)
    got = compiled.load(path)  # the user's own: trusted (whoever wrote it is the user)
    assert got is not None and got.field("co2").unit == "forged" != real.field("co2").unit


@pytest.mark.parametrize("where", ["directory", "file"])
@pytest.mark.parametrize("how", ["owned by another user", "group-writable",
                                 "world-writable"])
def test_a_forged_entry_another_user_could_write_is_never_used(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch, where: str,
        how: str) -> None:
    path, real, file = setup(tmp_path, cache)
    target = cache if where == "directory" else file
    if how == "owned by another user":
        not_mine(target, monkeypatch)
    else:
        target.chmod(target.stat().st_mode | (0o020 if how == "group-writable" else 0o002))
    assert compiled.load(path) is None
    assert load_profile(path) == real == read_profile(path)[0]
    assert load_profile(path).field("co2").unit == "ppm"


def test_nothing_is_stored_in_a_directory_others_may_write(
        tmp_path: Path, cache: Path) -> None:
    cache.mkdir(parents=True)
    cache.chmod(0o777)
    path = Path(shutil.copy(bundled_dir() / "huiwen-aq.yaml", tmp_path))
    load_profile(path)
    assert list(cache.iterdir()) == []


def test_a_link_to_a_file_another_user_owns_is_not_followed_into_trust(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path, _, file = setup(tmp_path, cache)
    elsewhere = tmp_path / "planted.pickle"
    file.rename(elsewhere)
    file.symlink_to(elsewhere)
    not_mine(elsewhere, monkeypatch)
    assert compiled.load(path) is None


def test_with_no_user_ids_as_on_windows_the_cache_is_the_users_local_app_data(
        tmp_path: Path, cache: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Windows's ``os`` has no ``getuid`` and its ``os.stat`` no owner: the cache goes to
    ``%LOCALAPPDATA%`` (private by its ACL), is written and read back there, and the
    group/other bits a Windows stat shows (0o666 for any writable file) refuse nothing."""
    monkeypatch.delattr(os, "getuid")
    local = tmp_path / "AppData" / "Local"
    monkeypatch.setenv("LOCALAPPDATA", str(local))
    here = local / "rtupoll" / "cache" / "profiles"
    assert compiled.directory() == here
    path, real, file = setup(tmp_path, here)
    assert file.parent == here and not cache.exists()
    file.chmod(0o666)  # what os.stat says of every writable file on Windows
    got = compiled.load(path)
    assert got is not None and got.field("co2").unit == "forged" != real.field("co2").unit


@pytest.mark.parametrize(("uid", "mode", "mine"), [
    (1000, 0o100600, True), (1001, 0o100600, False), (1000, 0o100620, False),
    (1000, 0o100602, False)])
def test_the_owner_rule_where_there_are_user_ids(uid: int, mode: int, mine: bool) -> None:
    st = os.stat_result((mode, 0, 0, 1, uid, 0, 0, 0, 0, 0))
    assert compiled.owned(st, lambda: 1000) is mine
    assert compiled.owned(st, None) is True  # no user ids (Windows): the folder's ACL decides
