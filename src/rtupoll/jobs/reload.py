"""SIGHUP for ``rtupoll poll``: reopen the output file, reload the site file.

A service (``rtupoll.jobs.services``) that, on SIGHUP, first reopens ``--output``
(logrotate moved it away: records continue in a new file at the same path), then
reads the site file again and hands it to ``Scheduler.reload``: devices added,
removed or changed take effect, ports that did not change stay open. A file with
a mistake changes nothing: the running configuration goes on and the mistake is
logged as ``file:line: path: message``.

A SIGHUP is also what a terminal sends when it goes away (a closed window, a dropped
SSH session). ``poll`` started on a terminal that has since hung up stops as SIGTERM
stops it, instead of polling on unseen and holding the port; one started without a
terminal (a service) reloads, and so does one under ``nohup`` (SIGHUP ignored).

Windows has no SIGHUP (``signal.HANGUP`` is None there): the service then starts and
stops doing nothing, ``poll`` runs as everywhere, and a changed site file takes a
restart (docs/polling.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from rtupoll.errors import RtupollError
from rtupoll.jobs.services import Reload, Service

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading

log = logging.getLogger("rtupoll.reload")

HANGUP: signal.Signals | None = getattr(signal, "SIGHUP", None)  # None on Windows


class Reopenable(Protocol):
    """The record output (``ui.record_writer.RecordWriter``): its file reopened, and the
    reloaded site followed (records that name a device's bus)."""

    def reopen(self) -> None: ...

    def follow(self, site: Site) -> None: ...


class ReloadService(Service):
    """SIGHUP -> reopen the output, reload the site (when there is a site file)."""

    def __init__(self, load: Callable[[], Site] | None, output: Reopenable | None = None,
                 *, notify: Callable[[str], None] | None = None,
                 peers: Sequence[Service] = (), serves: bool = False) -> None:
        """``peers``: the services that follow a reload (``Service.on_reload``); ``serves``:
        a gateway runs among them, so a changed ``serve:`` can be applied."""
        self.load, self.output, self.notify = load, output, notify
        self.peers, self.serves = peers, serves
        self.reloads = 0  # completed reloads, whatever their outcome
        self._scheduler: Scheduler | None = None
        self._pending: asyncio.Task[None] | None = None
        self._again = False
        self._was: signal.Handlers | int | Callable[..., object] | None = None
        self._on_terminal = False  # started on a terminal (and not under nohup)

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = scheduler
        if HANGUP is None:  # no SIGHUP (Windows): nothing to reload on
            return
        was = signal.getsignal(HANGUP)
        self._on_terminal = was != signal.SIG_IGN and _has_terminal()
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            asyncio.get_running_loop().add_signal_handler(HANGUP, self.hangup)
            self._was = was

    def hangup(self) -> None:
        """The signal handler: one reload at a time; a SIGHUP during one runs another.
        The terminal this process was started on gone: a stop, as by SIGTERM."""
        if self._on_terminal and not _has_terminal():
            log.warning("the terminal hung up: stopping", extra={"event": "stop"})
            os.kill(os.getpid(), signal.SIGTERM)
            return
        if self._pending is not None and not self._pending.done():
            self._again = True
            return
        self._pending = asyncio.get_running_loop().create_task(self._reload())

    async def _reload(self) -> None:
        while True:
            self._again = False
            await self.reload_once()
            if not self._again:
                return

    async def reload_once(self) -> None:
        if self.notify is not None:
            self.notify("reloading")
        if self.output is not None:
            try:
                self.output.reopen()
                log.info("reopened the output file", extra={"event": "reopen"})
            except OSError as exc:
                log.error("cannot reopen the output file: %s (writing on to the old one)",
                          exc, extra={"event": "reopen", "error": str(exc)})
        if self.load is not None and self._scheduler is not None:
            try:
                site = self.load()
            except RtupollError as exc:
                log.error("reload refused, polling goes on unchanged: %s", exc,
                          extra={"event": "reload", "error": str(exc)})
            else:
                await self._apply(site)
        self.reloads += 1
        if self.notify is not None:
            self.notify("reloaded")

    async def _apply(self, site: Site) -> None:
        assert self._scheduler is not None
        prepared: list[Reload] = []
        served = [b.name for b in site.buses if b.serve is not None]
        if served and not self.serves:
            log.error("reload refused, polling goes on unchanged: serve: on %s needs a "
                      "restart (rtupoll was started without a gateway)", ", ".join(served),
                      extra={"event": "reload", "error": "serve"})
            return
        try:  # e.g. the gateway binds a new serve: address first
            for peer in self.peers:
                prepared.append(await peer.on_reload(site))
        except RtupollError as exc:
            for p in prepared:
                await p.abort()
            log.error("reload refused, polling goes on unchanged: %s", exc,
                      extra={"event": "reload", "error": str(exc)})
            return
        if site.metrics != self._scheduler.site.metrics:
            log.warning("reload: metrics: %s takes effect at the next start",
                        site.metrics or "(none)", extra={"event": "reload"})
        changes = await self._scheduler.reload(site)
        for p in prepared:
            changes += await p.commit(self._scheduler)
        if self.output is not None:
            self.output.follow(self._scheduler.site)
        for c in changes:
            log.info("reload: %s", c, extra={"event": "reload"})
        if not changes:
            log.info("reload: nothing changed", extra={"event": "reload"})

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        return None

    async def stop(self) -> None:
        if self._was is not None and HANGUP is not None:  # what SIGHUP did before (nohup)
            asyncio.get_running_loop().remove_signal_handler(HANGUP)
            signal.signal(HANGUP, self._was)
            self._was = None
        if self._pending is not None and not self._pending.done():
            self._pending.cancel()
            await asyncio.gather(self._pending, return_exceptions=True)


def _has_terminal() -> bool:
    """Whether this process has a controlling terminal (one that hung up has none)."""
    try:
        os.close(os.open("/dev/tty", os.O_RDWR | os.O_NOCTTY))
    except OSError:
        return False
    return True
