"""``poll -o FILE``: records appended whole, or not at all.

Each batch (one device cycle's records) goes to the end of the file in one ``write``
(``O_APPEND``); a write that fails part-way (a full disk, a file size limit) is cut
back to where the batch began, so the file never holds half a line. Then the file
output stops with one logged error, and everything else ``poll`` runs (the scheduler,
the gateway, MQTT, ``/metrics``) goes on; a SIGHUP (``reopen``) tries again, e.g. once
space was freed.

A file whose last line an earlier run left unfinished (power loss, ``kill -9`` half-way
through a write before this scheme) gets that partial line cut off, with a log line,
before anything is appended: a record is never glued onto a fragment.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

log = logging.getLogger("rtupoll.output")
TAIL = 1 << 16  # bytes searched back for the last newline


# Windows has no O_CLOEXEC (a descriptor is not inherited there unless asked) and no
# pread, and opens in text mode unless O_BINARY (a "\n" written would be "\r\n")
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_BINARY = getattr(os, "O_BINARY", 0)


def _pread(fd: int, n: int, offset: int) -> bytes:
    if hasattr(os, "pread"):
        return os.pread(fd, n, offset)
    os.lseek(fd, offset, os.SEEK_SET)  # (O_APPEND: writes still go to the end)
    return os.read(fd, n)


class OutputFile:
    """A text file ``RecordWriter`` writes through (``write`` and a no-op ``flush``)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.failed = ""  # why the output stopped ("": writing)
        self.fresh = True  # the file was empty when opened (a CSV header is due)
        self.fd = self._open()

    def _open(self) -> int:
        fd = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT | _CLOEXEC | _BINARY,
                     0o644)
        try:
            self._trim(fd)
        except BaseException:
            os.close(fd)
            raise
        return fd

    def _trim(self, fd: int) -> None:
        """Cut off a partial last line left by an earlier run."""
        size = os.fstat(fd).st_size
        self.fresh = size == 0
        if not size or _pread(fd, 1, size - 1) == b"\n":
            return
        start = max(0, size - TAIL)
        tail = _pread(fd, size - start, start)
        keep = start + tail.rfind(b"\n") + 1 if b"\n" in tail else 0 if start == 0 else size
        if keep == size:  # no newline within reach: a line too long to judge, left as it is
            os.write(fd, b"\n")
            return
        os.ftruncate(fd, keep)
        self.fresh = keep == 0
        log.warning("%s: cut off a partial last line (%d bytes) an earlier run left",
                    self.path, size - keep, extra={"event": "output"})

    def write(self, text: str) -> None:
        if self.failed or not text:
            return
        data = memoryview(text.encode("utf-8"))
        start = os.fstat(self.fd).st_size
        try:
            while data:
                data = data[os.write(self.fd, data):]
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, start)  # nothing half-written
            self.failed = exc.strerror or str(exc)
            log.error("cannot write %s: %s; the file output stops here (whole records "
                      "only; SIGHUP tries again), polling and the other outputs go on",
                      self.path, self.failed, extra={"event": "output", "error": self.failed})
        else:
            self.fresh = False

    def flush(self) -> None:
        """Each ``write`` is already in the file."""

    def reopen(self) -> None:
        """SIGHUP: continue in the file now at ``path`` (logrotate), and try again after
        a failure."""
        fd = self._open()
        old, self.fd, self.failed = self.fd, fd, ""
        os.close(old)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)
