"""The compiled profile cache: validated profiles kept pickled, so that the next command
that needs the same unchanged profile neither imports the YAML parser nor validates it.

One file per profile path, in ``$XDG_CACHE_HOME/rtupoll/profiles`` (``~/.cache/...``
when that is unset; ``%LOCALAPPDATA%\\rtupoll\\cache\\profiles`` on Windows). ``load``
takes a cached profile only when

- the code that built it is this code: the stamp is the path, mtime and size of each
  module whose classes or rules make a ``Profile`` (as they were when the process first
  asked), so a changed rtupoll never takes objects an older one made;
- every file it was read from (the profile and each one it ``extends``) still holds the
  very bytes parsed (bytes, not mtimes: an edit in the same second is seen), and
- each ``extends`` still finds the same file (the search path, or a new file next to the
  profile, can change which parent is found).

Anything else (no file, a corrupt, truncated, foreign or oversized one, an unwritable
directory) means "not cached": the caller reads the profile, which also gives every
error as ``file:line``; a failure is never cached. ``$RTUPOLL_NO_PROFILE_CACHE`` (any
non-empty value) switches the cache off; deleting the directory is always safe.

A process keeps what it loaded from a cache file: loading the same profile again (a
reload, the library of each simulated bus) while the cache file is the same file (its
inode, change time and size) checks the profile's files as above but neither reads nor
unpickles the cache file again (a library of 24 profiles loads in 5 ms instead of 19).

Only the user's own cache is trusted: the directory and each file must be owned by the
user and writable by no one else (a shared ``XDG_CACHE_HOME``, a directory another user
created in advance, a CI cache); anything else is "not cached" (the profile file is
read) and nothing is stored there. Windows has no owner or mode bits to check: its
cache is in the user's ``%LOCALAPPDATA%``, private by that folder's ACL (``_own``).
Loading a pickle can run code; besides the ownership check, the unpickler here builds
nothing but the model's own classes, so a planted file cannot call anything else.
"""

from __future__ import annotations

# the C pickler itself: pickle.py around it costs each start a millisecond more
import _pickle as pickle
import binascii
import dataclasses
import io
import os
import stat
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from rtupoll.config.paths import find_parent
from rtupoll.model import codec, profile, transforms
from rtupoll.model.profile import Profile
from rtupoll.rtu import functions

OFF_ENV = "RTUPOLL_NO_PROFILE_CACHE"  # set and not empty: no cache
MAX_BYTES = 8 << 20  # a larger cache file is not read (the largest bundled one: 19 kB)

# the modules whose classes a Profile is made of, and (below) those whose rules build it
_MODEL = {m.__name__: m for m in (profile, codec, transforms, functions)}
_HERE = os.path.dirname(__file__)
_CODE = (*(str(m.__file__) for m in _MODEL.values()),
         *(os.path.join(_HERE, name) for name in ("profile_file.py", "scale_by.py", "yamlsrc.py",
                                                     "compiled.py", "transform_key.py")))


class Source(NamedTuple):
    """A file a profile was read from: the profile's own, or one it extends."""

    path: Path  # as it was opened
    data: bytes  # what was parsed
    extends: str  # the id of the profile it extends, "" for none


def directory() -> Path:
    """Where the cache lives (XDG: an unset, empty or relative variable is ignored; on
    Windows the user's own ``%LOCALAPPDATA%``, whatever XDG says: see ``_own``)."""
    if not hasattr(os, "getuid"):
        local = os.environ.get("LOCALAPPDATA", "")
        if os.path.isabs(local):
            return Path(local, "rtupoll", "cache", "profiles")
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base, "rtupoll", "profiles")


def load(path: Path) -> Profile | None:
    """``path``'s profile as reading the file would give it, or None: not cached, or not
    any more (then read the file)."""
    if os.environ.get(OFF_ENV):
        return None
    try:
        return _load(path)
    except Exception:  # whatever is wrong with the cache, reading the file is right
        return None


def store(path: Path, built: Profile, sources: Sequence[Source]) -> None:
    """Keep ``built``, just read from ``sources``, for the next ``load(path)``."""
    if os.environ.get(OFF_ENV):
        return
    key = os.path.abspath(path)
    try:
        chain = tuple((str(s.path.resolve()), s.data, s.extends) for s in sources)
        payload = pickle.dumps(built, -1)
        data = pickle.dumps((_stamp(), key, chain, payload), -1)
        if len(data) <= MAX_BYTES:
            _write(_file(key), data)
    except OSError:  # no home, a read-only cache, a full disk: read the file next time
        pass


def _own(st: os.stat_result) -> bool:
    return owned(st, getattr(os, "getuid", None))


def owned(st: os.stat_result, getuid: Callable[[], int] | None) -> bool:
    """Whether a cache directory or file is the user's alone: owned by the user, and
    neither group- nor other-writable (anyone else who could write there could plant a
    forged profile: a wrong value reported ``ok``, a write aimed at another register).

    Windows has neither (``os.stat`` gives no owner and mode bits that only mirror the
    read-only attribute): there the cache is in ``%LOCALAPPDATA%`` (``directory``), in
    the user's profile, whose ACL lets only the user, SYSTEM and the administrators in;
    another user cannot plant a file there, so nothing more is checked."""
    if getuid is None:
        return True
    return st.st_uid == getuid() and not st.st_mode & 0o022


def _load(path: Path) -> Profile | None:
    key = os.path.abspath(path)  # not resolved: the id must match the name as given
    if not _own(os.stat(directory())):
        return None
    file = _file(key)
    st, seen = os.stat(file), _SEEN.get(file)
    if seen is not None and seen[0] == _identity(st) and _readable(st):
        _, chain, cached = seen  # this very file, loaded before: only its sources may differ
        if not _unchanged(path, chain):
            return None
    else:
        with file.open("rb") as fh:
            st = os.fstat(fh.fileno())  # the file opened, whatever a link pointed to
            if not _readable(st):
                return None
            data = fh.read(MAX_BYTES + 1)
        if len(data) > MAX_BYTES:
            return None
        # the profile is pickled apart, and unpickled only once its files are known
        # unchanged
        stamp, stored_key, chain, payload = _unpickle(data)
        if stamp != _stamp() or stored_key != key or not _unchanged(path, chain):
            return None
        cached = _unpickle(payload)
        if not isinstance(cached, Profile):
            return None
        _SEEN[file] = (_identity(st), chain, cached)
    # the same file named another way (relative, absolute) keeps the name it was given
    return cached if cached.path == str(path) else dataclasses.replace(cached, path=str(path))


# the cache files this process has loaded, each with what it held: loaded again while it
# is the same file (same inode, change time and size), it is neither read nor unpickled
_SEEN: dict[Path, tuple[tuple[int, int, int, int], Sequence[tuple[str, bytes, str]], Profile]] = {}


def _identity(st: os.stat_result) -> tuple[int, int, int, int]:
    return st.st_dev, st.st_ino, st.st_ctime_ns, st.st_size


def _readable(st: os.stat_result) -> bool:
    return _own(st) and stat.S_ISREG(st.st_mode) and st.st_size <= MAX_BYTES


def _unchanged(path: Path, chain: Sequence[tuple[str, bytes, str]]) -> bool:
    """Whether each file of ``chain`` holds the bytes parsed, each ``extends`` finding the
    same file again the way ``profile_file`` finds it (from the path as given). Only
    regular files are compared: reading a pipe would take bytes the parser then misses."""
    current: Path | None = path
    for resolved, data, parent in chain:
        if current is None or not current.is_file() or str(current.resolve()) != resolved:
            return False
        with current.open("rb") as fh:
            if fh.read(len(data) + 1) != data:
                return False
        current = find_parent(parent, current) if parent else None
    return bool(chain) and current is None


def _stamp() -> tuple[tuple[str, int, int], ...]:
    """The code of this process: its files as they were when it first asked (a process
    running while rtupoll is upgraded under it neither takes the new code's profiles nor
    stamps its own as the new code's)."""
    global _STAMP
    if _STAMP is None:
        _STAMP = tuple((f, st.st_mtime_ns, st.st_size) for f in _CODE for st in [os.stat(f)])
    return _STAMP


_STAMP: tuple[tuple[str, int, int], ...] | None = None


def _file(key: str) -> Path:
    """A profile path's cache file: its name, for people, and a CRC of the whole path
    (hashlib would cost 8 ms to import); two paths with one CRC only take turns."""
    crc = binascii.crc32(os.fsencode(key))
    return directory() / f"{os.path.basename(key)[:64]}-{crc:08x}.pickle"


def _write(target: Path, data: bytes) -> None:
    """Atomically: a process reading at the same time sees the old file or the new one."""
    import tempfile  # only after a profile was read, which costs far more

    target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    if not _own(os.stat(target.parent)):  # another's (or a shared) directory: no cache
        return
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, target)
    except BaseException:
        os.unlink(tmp)
        raise


class _Unpickler(pickle.Unpickler):
    """Builds only the classes defined in ``_MODEL``'s modules: whoever wrote a cache file,
    loading it calls nothing else."""

    def find_class(self, module: str, name: str) -> Any:
        found = getattr(_MODEL.get(module), name, None)
        if isinstance(found, type) and found.__module__ == module:
            return found
        raise pickle.UnpicklingError(f"{module}.{name} is not part of a profile")


def _unpickle(data: bytes) -> Any:
    return _Unpickler(io.BytesIO(data)).load()
