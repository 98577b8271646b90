"""What runs beside the scheduler for the life of ``rtupoll poll``: publishers and servers.

A ``Service`` is started once the ports are open, is handed every device cycle's
readings (``DevicePoller.stats.state`` says whether the device is online), follows a
reload of the site file (SIGHUP), and is stopped before the ports close. MQTT,
Prometheus, the Modbus TCP gateway, the dashboard, the state log, SIGHUP itself and
systemd's notify protocol are services; the record writer and the live table are not
(they are the command's own output). ``rtupoll.app.services`` builds them and hands
each what it needs of the others: no service looks for another.

A service subclasses ``Service`` and writes ``start``, ``on_readings`` and ``stop``;
``on_reload``, ``collectors`` and ``footer`` have defaults that do nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from rich.console import RenderableType

    from rtupoll.config.site import Site
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading


class Reload(Protocol):
    """A service's part of one reload, readied by ``Service.on_reload``: ``commit`` once
    the scheduler has taken the new site, or ``abort`` when the reload is refused."""

    async def commit(self, scheduler: Scheduler) -> list[str]:
        """Follow the new site; what changed, one log line each."""
        ...

    async def abort(self) -> None:
        """Give back what ``on_reload`` took (a listener bound in advance); never raises."""
        ...


class Unchanged:
    """The ``Reload`` of a service that has nothing to ready."""

    async def commit(self, scheduler: Scheduler) -> list[str]:
        return []

    async def abort(self) -> None:
        return None


class Follow(Unchanged):
    """The ``Reload`` of a service that readies nothing and follows the new site at
    ``commit``: ``then(scheduler)`` says what changed."""

    def __init__(self, then: Callable[[Scheduler], list[str]]) -> None:
        self.then = then

    async def commit(self, scheduler: Scheduler) -> list[str]:
        return self.then(scheduler)


class Service(Protocol):
    async def start(self, scheduler: Scheduler) -> None:
        """Begin (connect, bind, publish discovery); ``RtupollError`` ends ``poll`` cleanly."""
        ...

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        """One device cycle's readings, in field order; must not block the event loop."""
        ...

    async def stop(self) -> None:
        """Say goodbye (retained offline states, closing listeners); never raises."""
        ...

    async def on_reload(self, site: Site) -> Reload:
        """SIGHUP, before the scheduler takes ``site``: ready what the new site needs (bind
        a new listen address). ``RtupollError`` refuses the whole reload: nothing changes."""
        return Unchanged()

    def collectors(self) -> Sequence[object]:
        """Prometheus collectors of what this service counts, for ``/metrics``."""
        return ()

    def footer(self) -> RenderableType | None:
        """Lines under the live table (None: nothing to say now)."""
        return None
