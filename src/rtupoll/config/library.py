"""The profile library: finding profile files, and loading them.

The library is every profile on the search path (``--profiles`` directories,
``$RTUPOLL_PROFILES``, then the bundled ones). ``load_profile`` takes a profile from the
compiled profile cache (``compiled``) when none of its files changed, and otherwise has
``profile_file`` read and validate it: so a command that needs one unchanged profile
does not import the YAML parser at all.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

from rtupoll.config.paths import bundled_dir, search_path
from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.model.profile import Profile


def load_profile(path: Path) -> Profile:
    """Read and validate one profile file (and the profiles it ``extends``), or take it
    from the cache when that still holds what reading it would give."""
    from rtupoll.config import compiled  # not at the top: it uses find_parent from here

    profile = compiled.load(path)
    if profile is None:
        from rtupoll.config.profile_file import read_profile

        profile, sources = read_profile(path)
        compiled.store(path, profile, sources)
    return profile


_WARNED: set[str] = set()


def note_use(profile: Profile) -> Profile:
    """Say once per run, in one log line, that a profile about to read a device is
    unverified (its values may be wrong); returns the profile."""
    if not profile.provenance.verified and profile.id not in _WARNED:
        _WARNED.add(profile.id)
        import logging

        logging.getLogger("rtupoll.profiles").warning(
            "warning: profile %s is %s: nobody checked its register map against the vendor's "
            "document, so its values may be wrong ('rtupoll profiles show %s')",
            profile.id, profile.provenance.label, profile.id)
    return profile


@frozen
class Library:
    """Every profile on the search path, by id; a user's profile shadows a bundled one."""

    profiles: Mapping[str, Profile]

    def get(self, pid: str) -> Profile:
        if pid in self.profiles:
            return self.profiles[pid]
        from rtupoll.model.names import close_names

        hint = close_names(pid, self.profiles)
        raise UsageError(f"no profile {pid!r}" + (f" (did you mean {hint[0]!r}?)" if hint else "")
                         + "; see 'rtupoll profiles list'")


def load_library(extra: Iterable[Path] = ()) -> Library:
    found: dict[str, Profile] = {}
    for directory in search_path(extra):
        if not directory.is_dir():
            if directory != bundled_dir():
                raise UsageError(f"profile directory {directory} does not exist")
            continue
        for path in sorted(directory.glob("*.yaml")):
            profile = load_profile(path)
            found.setdefault(profile.id, profile)
    return Library(found)


def load_one(pid: str, extra: Iterable[Path] = ()) -> Profile:
    """One profile by id, or a path to a YAML file; loads only what it needs."""
    if pid.endswith((".yaml", ".yml")):
        return load_profile(Path(pid))
    for directory in search_path(extra):
        path = directory / f"{pid}.yaml"
        if path.is_file():
            return load_profile(path)
    return load_library(extra).get(pid)
