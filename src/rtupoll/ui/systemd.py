"""systemd's notify protocol, in a few lines: READY, WATCHDOG, RELOADING, STOPPING.

With ``Type=notify`` systemd sets ``NOTIFY_SOCKET`` (a datagram socket path, or an
abstract one starting with ``@``) and waits for ``READY=1``; with ``WatchdogSec=`` it
sets ``WATCHDOG_USEC`` and restarts the service when ``WATCHDOG=1`` stops coming.
``Notifier`` is a service (``rtupoll.jobs.services``): ready once the ports are open
and the other services run, then a watchdog ping at half the period from the event
loop, so a hung loop stops the pings. Without ``NOTIFY_SOCKET`` it does nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time
from typing import TYPE_CHECKING

from rtupoll.jobs.services import Service
from rtupoll.numbers import count

if TYPE_CHECKING:
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading


def notify(message: str, socket_path: str | None = None) -> bool:
    """Send one notification (``READY=1``...); False when there is no socket or it fails."""
    path = socket_path if socket_path is not None else os.environ.get("NOTIFY_SOCKET", "")
    if not path:
        return False
    address = "\0" + path[1:] if path.startswith("@") else path
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(address)
            s.sendall(message.encode())
    except OSError:
        return False
    return True


def watchdog_period() -> float | None:
    """Seconds between pings systemd expects (``WATCHDOG_USEC``), halved; None if unset."""
    usec = os.environ.get("WATCHDOG_USEC", "")
    pid = os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) <= 0 or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 1e6 / 2


class Notifier(Service):
    """READY=1 when polling starts, WATCHDOG=1 while the event loop runs, STOPPING=1."""

    def __init__(self) -> None:
        self.enabled = bool(os.environ.get("NOTIFY_SOCKET"))
        self._pinger: asyncio.Task[None] | None = None

    async def start(self, scheduler: Scheduler) -> None:
        if not self.enabled:
            return
        notify(f"READY=1\nMAINPID={os.getpid()}\nSTATUS=polling "
               f"{count(sum(len(b.devices) for b in scheduler.buses), 'device')}")
        period = watchdog_period()
        if period:
            self._pinger = asyncio.create_task(self._ping(period))

    def reloading(self) -> None:
        if self.enabled:
            usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
            notify(f"RELOADING=1\nMONOTONIC_USEC={usec}")

    def reloaded(self, status: str) -> None:
        if self.enabled:
            notify(f"READY=1\nSTATUS={status}")

    async def _ping(self, period: float) -> None:
        while True:
            notify("WATCHDOG=1")
            await asyncio.sleep(period)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        return None

    async def stop(self) -> None:
        if self._pinger is not None:
            self._pinger.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._pinger
        if self.enabled:
            notify("STOPPING=1")
