"""The gateway as a ``rtupoll.jobs.services.Service``: one ``Gateway`` per bus with
``serve`` set, sharing the line with that bus's poller (``BusPoller.share_line``).

On SIGHUP (``rtupoll.jobs.reload`` calls ``on_reload``) each bus's new ``serve:`` takes
effect: new rules on the same listener at once (clients the new ``allow:`` excludes are
disconnected), a new address re-bound (the new listener first: a reload that cannot bind
it is refused whole), a bus no longer served closed."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.gateway.server import Gateway, listen
from rtupoll.gateway.turns import Turns
from rtupoll.jobs.services import Service

if TYPE_CHECKING:
    from rich.console import RenderableType

    from rtupoll.config.site import Site
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading


_LOG = logging.getLogger("rtupoll.gateway")


def to_log(line: str) -> None:
    """The gateway's refusals and closed connections to the ``rtupoll`` log (stderr,
    text or JSON)."""
    _LOG.warning(line, extra={"event": "gateway"})


def to_info(line: str) -> None:
    """A client's counters when it disconnects."""
    _LOG.info(line, extra={"event": "gateway"})


class GatewayService(Service):
    def __init__(self, *, log: Callable[[str], None] | None = None,
                 info: Callable[[str], None] | None = None) -> None:
        self.gateways: list[Gateway] = []
        self._log, self._info = log, info

    async def start(self, scheduler: Scheduler) -> None:
        for bp in scheduler.buses:
            cfg = bp.config.serve
            if cfg is None:
                continue
            turns = Turns()
            gw = Gateway(cfg, bp, turns, log=self._log, info=self._info)
            await gw.start()
            bp.share_line(turns.turn)
            self.gateways.append(gw)

    async def on_reload(self, site: Site) -> GatewayReload:
        """SIGHUP, before the scheduler takes ``site``: bind every listen address the new
        ``serve:`` entries add, so that a reload that cannot serve them is refused whole
        (``PortError``, nothing changed) rather than half applied."""
        return await GatewayReload.prepare(self, site)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        for gw in self.gateways:
            if dev in gw.poller.devices:
                gw.on_readings(dev, readings)

    async def stop(self) -> None:
        for gw in self.gateways:
            await gw.stop()

    def snapshot(self) -> list[dict[str, Any]]:
        """Per bus: where it listens and each client's counters (JSON-ready)."""
        return [{"bus": gw.poller.config.name, "listen": gw.config.url,
                 "pending": gw.pending, "clients": [c.record() for c in gw.clients]}
                for gw in self.gateways]

    def collectors(self) -> list[object]:
        """Its per-client counters for ``/metrics`` (``outputs.metrics`` registers them)."""
        from rtupoll.gateway.metrics import GatewayCollector

        return [GatewayCollector(lambda: self.gateways)]

    def footer(self) -> RenderableType | None:
        """The live table's lines about the gateways' clients."""
        from rtupoll.gateway.footer import render

        return render(self.gateways) if self.gateways else None


def _listen_key(cfg: ServeConfig) -> tuple[str, str, int]:
    return cfg.framing, cfg.host, cfg.port


class GatewayReload:
    """A reload's gateways: listeners bound in advance (``prepare``), then ``commit``
    (after ``Scheduler.reload``) or ``abort``."""

    def __init__(self, service: GatewayService, site: Site) -> None:
        self.service, self.site = service, site
        self.bound: dict[tuple[str, str, int], asyncio.Server] = {}
        self._ready: dict[tuple[str, str, int], Gateway] = {}

    @classmethod
    async def prepare(cls, service: GatewayService, site: Site) -> GatewayReload:
        self = cls(service, site)
        running = {(gw.poller.config.port, _listen_key(gw.asked)) for gw in service.gateways}
        try:
            for bus in site.buses:
                if bus.serve is None or (bus.port, _listen_key(bus.serve)) in running:
                    continue
                key = _listen_key(bus.serve)
                self.bound[key] = await listen(bus.serve, self._dispatch(key))
        except BaseException:
            await self.abort()
            raise
        return self

    def _dispatch(self, key: tuple[str, str, int]) -> Callable[
            [asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]:
        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            gw = self._ready.get(key)
            if gw is None:  # between the bind and the commit: not serving yet
                writer.close()
                return
            await gw._handle(reader, writer)
        return handle

    async def abort(self) -> None:
        for server in self.bound.values():
            server.close()
        self.bound.clear()

    async def commit(self, scheduler: Scheduler) -> list[str]:
        """The scheduler has taken the site: each bus's gateway follows its ``serve:``."""
        svc = self.service
        old = {gw.poller.config.port: gw for gw in svc.gateways}
        kept: list[Gateway] = []
        changes: list[str] = []
        for bp in scheduler.buses:
            cfg = bp.config.serve
            if cfg is None:
                continue
            gw = old.pop(bp.config.port, None)
            if gw is not None and _listen_key(gw.asked) == _listen_key(cfg):
                if gw.poller is not bp:  # the bus was reopened: its new poller
                    gw.poller = bp
                    bp.share_line(gw.turns.turn)
                changes += gw.reconfigure(cfg)
                kept.append(gw)
                continue
            new = Gateway(cfg, bp, Turns(), log=svc._log, info=svc._info)
            await new.start(self.bound.pop(_listen_key(cfg)))
            self._ready[_listen_key(cfg)] = new
            bp.share_line(new.turns.turn)
            kept.append(new)
            if gw is not None:
                await gw.stop()
                changes.append(f"bus {bp.config.name}: serving {new.config.url} "
                               f"(no longer {gw.config.url})")
            else:
                changes.append(f"bus {bp.config.name}: serving {new.config.url}")
        for gw in old.values():
            await gw.stop()
            changes.append(f"bus {gw.poller.config.name}: no longer serving {gw.config.url}")
        await self.abort()  # anything bound and not taken
        svc.gateways[:] = kept
        return changes
