"""Where profile files are: the search path (``--profiles``, ``$RTUPOLL_PROFILES``, the
bundled profiles) and the parent file a profile ``extends``. Reads no profile: the
reader, the cache and the library all start from here."""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterable
from pathlib import Path

PROFILES_ENV = "RTUPOLL_PROFILES"  # extra profile directories, os.pathsep-separated


def find_parent(pid: str, child: Path) -> Path | None:
    """The file of the profile ``pid`` that the profile file ``child`` extends: next to
    ``child`` first, then on the search path."""
    for directory in [child.parent, *search_path()]:
        candidate = directory / f"{pid}.yaml"
        if candidate.is_file():
            return candidate
    return None


def bundled_dir() -> Path:
    """The package ``rtupoll.profiles`` (the repository's profiles/, installed as package
    data): its own directory, without importlib.resources and what that imports."""
    package = importlib.import_module("rtupoll.profiles")
    return Path(package.__file__ or ".").parent


def search_path(extra: Iterable[Path] = ()) -> list[Path]:
    """User directories first (``--profiles``, then $RTUPOLL_PROFILES), bundled last."""
    env = [Path(p) for p in os.environ.get(PROFILES_ENV, "").split(os.pathsep) if p]
    return [*extra, *env, bundled_dir()]
