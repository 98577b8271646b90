"""``poll``'s records on stdout or in ``-o FILE``: one whole batch per write, flushed.

A ``RecordWriter`` holds where the records go (a text stream; a stdout pipe's
``ui.pipe_writer.PipeWriter``, whose thread writes them; or the ``OutputFile`` of
``ui.outfile``: whole records or nothing) and their format (a ``ui.records.RecordFormat``:
JSON, CSV, Influx line protocol). No line is ever written in part. SIGHUP's reload
(``jobs.reload``) calls ``reopen`` (logrotate moved the file away: the records go on in a
new file at the same path) and ``follow`` (the reloaded site: which bus each device is
on, for the formats that name it).
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from rtupoll.ui.outfile import OutputFile
from rtupoll.ui.pipe_writer import PipeWriter

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.jobs.stats import Reading
    from rtupoll.ui.records import RecordFormat


class RecordWriter:
    """Records in ``form`` to ``out``; ``path``: the file ``out`` is, for ``reopen``."""

    def __init__(self, out: TextIO | OutputFile | PipeWriter, form: RecordFormat, *,
                 path: Path | None = None) -> None:
        self.out, self.form, self.path = out, form, path

    def write(self, readings: Sequence[Reading], state: str = "") -> asyncio.Event | None:
        """One device cycle's records (``state``: the device's state after it), whole; to
        a ``PipeWriter`` whose reader lags, the event set once it has caught up
        (``jobs.scheduler.Sink``)."""
        text = self.form.text(readings, state)
        if not text:
            return None
        if isinstance(self.out, PipeWriter):
            return self.out.write(text)
        self.out.write(text)
        self.out.flush()
        return None

    def reopen(self) -> None:
        """Continue in a new file at ``path`` (logrotate moved the old one away); a
        stream that is no file (stdout) goes on as it is."""
        if self.path is None:
            return
        if isinstance(self.out, OutputFile):
            self.out.reopen()
        else:
            old, self.out = self.out, OutputFile(self.path)
            old.close()
        self.form.restart(self.out.fresh)

    def follow(self, site: Site) -> None:
        """The site polled from now on (a reload): the format learns the devices' buses."""
        self.form.follow(site)
