"""What runs beside the scheduler for the life of ``rtupoll poll``: publishers and servers.

A ``Service`` is started once the ports are open, is handed every device cycle's
readings (``DevicePoller.stats.state`` says whether the device is online), and is
stopped before the ports close. MQTT, Prometheus and the Modbus TCP gateway are
services; the record writer and the live table are not (they are the command's own
output).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading


class Service(Protocol):
    async def start(self, scheduler: Scheduler) -> None:
        """Begin (connect, bind, publish discovery); ``RtupollError`` ends ``poll`` cleanly."""

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        """One device cycle's readings, in field order; must not block the event loop."""

    async def stop(self) -> None:
        """Say goodbye (retained offline states, closing listeners); never raises."""
