"""The gateway as a ``rtupoll.jobs.services.Service``: one ``Gateway`` per bus with
``serve`` set, sharing the line with that bus's poller (``BusPoller.turn``)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rtupoll.gateway.server import Gateway
from rtupoll.gateway.turns import Turns

if TYPE_CHECKING:
    from rich.console import RenderableType

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


class GatewayService:
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
            bp.turn = turns.turn
            self.gateways.append(gw)

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

    def collector(self) -> object:
        """Its per-client counters for ``/metrics`` (``outputs.metrics`` registers it)."""
        from rtupoll.gateway.metrics import GatewayCollector

        return GatewayCollector(self)

    def footer(self) -> RenderableType | None:
        """The live table's lines about the gateways' clients."""
        from rtupoll.gateway.footer import render

        return render(self.gateways) if self.gateways else None
