"""``rtupoll poll --http HOST:PORT``: the dashboard of this process, as a ``Service``.

Fed like the other services (``rtupoll.jobs.services``): every device cycle's readings
go into the trend rings and, when a browser listens, mark the device's ``device`` event
due: made once for every listener when the events are written, with the device's state,
health and reading times and only the fields whose reading changed since its last event.
Every ``BUS_EVERY`` seconds a ``buses`` event carries the buses' load and the gateway's
clients and queue. ``/metrics`` is served here too, from ``outputs.metrics``'s
collector, when ``prometheus_client`` is installed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from rtupoll.config.http_settings import merge
from rtupoll.config.mqtt_settings import default_gateway_id
from rtupoll.jobs.services import Service
from rtupoll.model.interpret import DISPLAY_UNITS, display_value
from rtupoll.ui.records import to_json
from rtupoll.web.server import Hub, Server
from rtupoll.web.state import Clocks, buses_event, device_delta, number, poll_state
from rtupoll.web.trend import TrendStore

if TYPE_CHECKING:
    from rtupoll.config.http_settings import HttpSettings
    from rtupoll.config.site import Site
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading
    from rtupoll.outputs.metrics import Exporter
    from rtupoll.web.server import Listener

log = logging.getLogger("rtupoll.web")
BUS_EVERY = 2.0  # seconds between ``buses`` events


class WebService(Service):
    """The dashboard beside the scheduler (a ``rtupoll.jobs.services.Service``)."""

    def __init__(self, settings: HttpSettings, *, title: str = "",
                 served: Callable[[], Sequence[dict[str, Any]]] = list,
                 say: Callable[[str], None] | None = None, others: Sequence[object] = (),
                 cli: HttpSettings | None = None, gateway: str | None = None) -> None:
        """``served``: the gateways' clients; ``others``: other services' collectors, for
        ``/metrics``; ``cli``: the command line's ``--http*``, over the site file's
        ``http:`` again at a reload; ``gateway``: the id MQTT publishes under (``--mqtt-id``,
        ``mqtt: gateway_id:``), else the host name's, as MQTT's default."""
        self.settings, self.title, self.served = settings, title, served
        self.say, self.cli = say, cli
        self.hub = Hub()
        self.trends = TrendStore(time.time())
        self.gateway = gateway or default_gateway_id()  # the id MQTT publishes under
        self.others: Sequence[Any] = others
        self.server = Server(settings, self)
        self._scheduler: Scheduler | None = None
        self._bus_of: dict[str, BusPoller] = {}
        self._prom: Exporter | None = None
        self._ticker: asyncio.Task[None] | None = None
        # per device: the hub's epoch and the signatures of the fields last sent
        self._sent: dict[str, tuple[int, dict[str, object]]] = {}

    @property
    def address(self) -> str:
        return self.server.address

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = scheduler
        self._prom = self._metrics(scheduler)
        await self.server.start()
        log.info("dashboard on %s", self.address, extra={"event": "http"})
        if self.say is not None:
            self.say(f"dashboard on {self.address}")
        self._ticker = asyncio.create_task(self._tick())

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        sched = self._scheduler
        if sched is None:
            return
        name = dev.config.name
        for r in readings:
            if r.value is not None and (v := number(r.value.output)) is not None:
                if r.field.unit in DISPLAY_UNITS:  # drawn in the unit it is shown in
                    shown = number(display_value(r.value)[0])
                    v = v if shown is None else shown
                self.trends.add(name, r.field.name, r.time, v)
        if self._prom is not None:
            self._prom.on_readings(dev, readings)
        bus = self._bus_of.get(name)
        if bus is None or dev not in bus.devices:
            self._bus_of = {d.config.name: bp for bp in sched.buses for d in bp.devices}
            bus = self._bus_of.get(name)
        if bus is not None:
            self.hub.publish("d:" + name, "device", lambda: self._delta(dev))

    async def on_reload(self, site: Site) -> WebReload:
        """A changed ``http:``: a new address bound first (a reload that cannot bind it is
        refused whole), new authentication at once; and the devices the site now has."""
        return await WebReload.prepare(self, merge(self.cli, site.http))

    def reloaded(self, scheduler: Scheduler) -> None:
        """The scheduler took a new site: other devices, perhaps other buses."""
        self._bus_of = {}
        if self._prom is not None:
            self._prom.follow(scheduler)
        self.trends.forget({d.config.name for d in scheduler.pollers()})
        self._sent.clear()
        self.hub.publish("state", "state", self._state_event)

    async def stop(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._ticker
        await self.server.stop()

    # -- the source the server shows ---------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        assert self._scheduler is not None
        return poll_state(self._scheduler, title=self.title, served=self.served(),
                          gateway=self.gateway)

    def trend(self, key: str, field: str) -> dict[str, Any]:
        return self.trends.series(key, field, time.time())

    def metrics(self, accept: str) -> tuple[bytes, str] | None:
        return self._prom.render(accept) if self._prom is not None else None

    # -----------------------------------------------------------------------------

    def _metrics(self, scheduler: Scheduler) -> Exporter | None:
        """``outputs.metrics``' exporter, the one ``--metrics`` serves, served here."""
        try:
            import prometheus_client  # noqa: F401
        except ImportError:
            return None
        from rtupoll.outputs.metrics import Exporter

        return Exporter(scheduler, self.others)

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(BUS_EVERY)
            self.hub.publish("buses", "buses", self._buses)

    def _state_event(self) -> str:
        self.hub.epoch += 1  # every device's next event carries every field
        return to_json(self.snapshot())

    def _delta(self, dev: DevicePoller) -> str:
        """The device's event, made when it is sent: the fields changed since its last
        event, or every field after a snapshot went out (``Hub.epoch``)."""
        name, epoch = dev.config.name, self.hub.epoch
        got = self._sent.get(name)
        if got is None or got[0] != epoch:
            got = self._sent[name] = (epoch, {})
        return to_json({"gateway": self.gateway,
                        "device": device_delta(dev, Clocks(), got[1])})

    def _buses(self) -> str:
        assert self._scheduler is not None
        return to_json(buses_event(self._scheduler, self.served(), self.gateway))


class WebReload:
    """The dashboard's part of a reload (a ``rtupoll.jobs.services.Reload``): the new
    listener bound in ``prepare``, made the one (and the new authentication taken) at
    ``commit``."""

    def __init__(self, service: WebService, settings: HttpSettings | None,
                 bound: Listener | None) -> None:
        self.service, self.settings, self.bound = service, settings, bound

    @classmethod
    async def prepare(cls, service: WebService, settings: HttpSettings | None) -> WebReload:
        old = service.server.settings if service.server.listener is not None else None
        bound = None
        if settings is not None and (old is None or _where(old) != _where(settings)):
            bound = await service.server.bind(settings)
        return cls(service, settings, bound)

    async def commit(self, scheduler: Scheduler) -> list[str]:
        svc, new = self.service, self.settings
        server = svc.server
        was = server.address if server.listener is not None else ""
        old = server.settings
        changes: list[str] = []
        if new is None:
            if was:
                await server.serve(old, None)
                changes.append(f"http: no longer serving the dashboard on {was}")
        else:
            await server.serve(new, self.bound or server.listener)
            svc.settings = new
            if server.address != was:
                changes.append(f"http: dashboard on {server.address}" +
                               (f" (no longer {was})" if was else ""))
            if (new.token, dict(new.users)) != (old.token, dict(old.users)):
                changes.append("http: authentication changed")
            if (limits := _limits(new)) != _limits(old):
                changes.append("http: limits now " + ", ".join(
                    f"{k} {v}" for k, v in limits.items()))
            if self.bound is not None and (warning := new.warning()):
                log.warning("%s", warning, extra={"event": "http"})
        self.bound = None
        svc.reloaded(scheduler)
        return changes

    async def abort(self) -> None:
        if self.bound is not None:
            await self.bound.stop()
            self.bound = None


def _limits(settings: HttpSettings) -> dict[str, str]:
    """The listener's limits as a reload's line shows them."""
    from rtupoll.config.http_settings import LIMITS

    return {k: (f"{v:g} s" if isinstance(v, float) else
                ", ".join(v) or "none" if isinstance(v, tuple) else str(v))
            for k in LIMITS for v in (getattr(settings, k),)}


def _where(settings: HttpSettings) -> tuple[str, int]:
    return settings.host, settings.port
