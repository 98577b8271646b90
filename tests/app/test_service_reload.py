"""A reload reaches every service through ``Service.on_reload`` (``rtupoll.jobs.services``):
no service compares sites or device lists to notice one. In-process, on the simulator."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from rtupoll.config.site import load_site
from rtupoll.gateway.service import GatewayService
from rtupoll.jobs.reload import ReloadService
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.jobs.services import Service, Unchanged
from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port


def served(path: Path, port: str, listen: int, *devices: tuple[str, str, int]) -> Path:
    text = f"buses:\n  - port: {port}\n    baudrate: 9600\n    serve: 127.0.0.1:{listen}\n" \
        "    devices:\n"
    text += "".join(f"      - {{name: {n}, profile: {p}, address: {a}, interval: 0.2}}\n"
                    for n, p, a in devices)
    path.write_text(text)
    return path


class Recorder(Service):
    """A service that only notes what reaches it."""

    def __init__(self) -> None:
        self.events: list[str] = []

    async def start(self, scheduler: Scheduler) -> None:
        self.events.append("start")

    def on_readings(self, dev: object, readings: object) -> None:
        return None

    async def stop(self) -> None:
        self.events.append("stop")


def test_the_gateway_learns_the_devices_a_reload_adds_and_every_service_is_asked(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("net-irnet-pro@1", "huiwen-aq@3", tick=None)
    path, port = tmp_path / "site.yaml", free_port()
    served(path, bus.port, port, ("gas", "net-irnet-pro", 1))

    async def main() -> tuple[set[int], set[int], list[str], object]:
        scheduler = Scheduler(load_site(path))
        gateways, other = GatewayService(), Recorder()
        reload = ReloadService(lambda: load_site(path), peers=[gateways, other], serves=True)
        await scheduler.open()
        await gateways.start(scheduler)
        await other.start(scheduler)
        await reload.start(scheduler)
        try:
            before = set(gateways.gateways[0].units)
            served(path, bus.port, port, ("gas", "net-irnet-pro", 1), ("air", "huiwen-aq", 3))
            await reload.reload_once()
            after = set(gateways.gateways[0].units)
            default = await other.on_reload(load_site(path))
        finally:
            await reload.stop()
            await other.stop()
            await gateways.stop()
            await scheduler.close()
        return before, after, other.events, default

    before, after, events, default = asyncio.run(main())
    assert (before, after) == ({1}, {1, 3})
    assert events == ["start", "stop"] and isinstance(default, Unchanged)
