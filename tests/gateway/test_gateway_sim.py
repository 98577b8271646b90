"""The gateway against the simulator, in-process: a pymodbus TCP client (an independent
peer) and raw sockets talk to simulated devices through ``rtupoll.gateway`` while the
scheduler polls the same line. The simulator's wire log shows what reached the line."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import io
import ipaddress
import struct
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from conftest import ANSWERED
from pymodbus.client import AsyncModbusTcpClient
from rich.console import Console

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.site import BusConfig, Site, from_specs
from rtupoll.gateway.service import GatewayService
from rtupoll.jobs.scheduler import Backoff, DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.live import PollView

Sim = Callable[..., SimulatedBus]


@dataclasses.dataclass
class Harness:
    service: GatewayService
    scheduler: Scheduler
    readings: list[Reading]
    logs: list[str]

    @property
    def port(self) -> int:
        return self.service.gateways[0].address[1]

    @property
    def gateway(self) -> Any:
        return self.service.gateways[0]

    async def client(self) -> AsyncModbusTcpClient:
        # 30 s: a hang guard (a loaded machine has taken more than 3 s to answer), no claim
        c = AsyncModbusTcpClient("127.0.0.1", port=self.port, timeout=30, retries=0)
        assert await c.connect()
        return c


@contextlib.asynccontextmanager
async def served(bus: SimulatedBus, devices: list[tuple[str, int]], *, interval: float = 0,
                 backoff: Backoff | None = None, device_timeout: float | None = None,
                 **serve: Any) -> AsyncIterator[Harness]:
    """``devices`` polled (``device_timeout``: theirs, else the profiles'), and served
    with ``serve``'s rules (``timeout``: for a unit that is not polled)."""
    cfg = ServeConfig("127.0.0.1", 0, **serve)
    if devices:
        site = from_specs(bus.port, devices, baudrate=115200, interval=interval,
                          timeout=device_timeout, check_serial=False)
        site = Site((dataclasses.replace(site.buses[0], serve=cfg),))
    else:
        site = Site((BusConfig("gw", bus.port, 115200, serve=cfg),))
    scheduler = Scheduler(site, backoff=backoff)
    logs: list[str] = []
    service = GatewayService(log=logs.append)
    readings: list[Reading] = []

    def sink(dev: DevicePoller, got: list[Reading]) -> None:
        service.on_readings(dev, got)
        readings.extend(got)

    stop = asyncio.Event()
    await scheduler.open()
    await service.start(scheduler)
    task = asyncio.create_task(scheduler.run(sink, stop))
    try:
        yield Harness(service, scheduler, readings, logs)
    finally:
        stop.set()
        await task
        await service.stop()
        await scheduler.close()


async def end_of(r: asyncio.StreamReader) -> bytes:
    """What arrives until the gateway closes the connection (a reset counts as closed)."""
    try:
        return await asyncio.wait_for(r.read(100), 30)  # (a hang guard: the close ends it)
    except ConnectionResetError:
        return b""


def garbage(bus: SimulatedBus) -> list[Any]:
    return [w for w in bus.wire if w.direction == "in" and "garbage" in w.note]


def test_pymodbus_reads_and_writes_while_the_poller_runs_flat_out(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "net-irnet-pro@1", tick=None)
    bus.set(3, "co2", 812)

    async def main() -> tuple[int, int, list[int], list[int]]:
        async with served(bus, [("huiwen-aq", 3), ("net-irnet-pro", 1)],
                          device_timeout=ANSWERED) as h:
            c = await h.client()
            before = len(h.readings)
            for i in range(30):
                rr = await c.read_input_registers(0x7536, count=5, device_id=3)
                assert not rr.isError(), rr
                assert rr.registers == list(bus.registers(3, "input", 0x7536, 5))
                w = await c.write_registers(0x0200, [0, 0x4248 + i], device_id=1)
                assert not w.isError(), w
            co2 = await c.read_input_registers(0x7539, count=1, device_id=3)
            got = await c.read_holding_registers(0x0200, count=2, device_id=1)
            c.close()
            during = len(h.readings) - before
            stats = h.gateway.clients[0]
            return during, stats.answered, list(co2.registers), list(got.registers)

    during, answered, co2, written = asyncio.run(main())
    assert answered == 62 and co2 == [812] and written == [0, 0x4248 + 29]
    assert during >= 30  # the poller's readings kept flowing meanwhile
    assert garbage(bus) == []  # no bad frame ever reached the line


def test_silent_devices_answer_0x0B_within_their_timeout(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:dead"], tick=None)

    async def main() -> tuple[list[tuple[int, float]], int, int]:
        async with served(bus, [("huiwen-aq", 3), ("radar-level", 4)], interval=0.05,
                          timeout=0.2, backoff=Backoff(base=0.05, cap=0.2, offline_after=1)) as h:
            c = await h.client()
            out = []
            for unit in (9, 4):  # nobody at 9 (the default timeout); 4 polled and dead
                t = time.monotonic()
                r = await c.read_holding_registers(0, count=1, device_id=unit)
                out.append((r.exception_code, time.monotonic() - t))
            radar = h.scheduler.pollers()[1]
            for _ in range(200):  # until the scheduler backs it off as offline
                if radar.stats.state.value == "offline":
                    break
                await asyncio.sleep(0.05)
            assert radar.stats.state.value == "offline"
            turns = h.gateway.turns.granted["clients"]
            r = await c.read_holding_registers(0, count=1, device_id=4)
            out.append((r.exception_code, 0.0))
            c.close()
            return out, turns, h.gateway.turns.granted["clients"]

    ((c9, t9), (c4, _), (c_off, _)), before, after = asyncio.run(main())
    assert (c9, c4, c_off) == (0x0B, 0x0B, 0x0B)
    assert t9 >= 0.2  # it waited for the device's timeout (the default 0.2 s here)
    assert after == before  # an offline device: answered at once, without a turn


def test_read_only_and_setup_register_refusals_are_counted_and_logged_once(sim: Sim) -> None:
    bus = sim("radar-level@4", tick=None)

    async def main() -> tuple[list[int | None], Any, list[str], int]:
        async with served(bus, [("radar-level", 4)], interval=0.2, device_timeout=ANSWERED) as h:
            c = await h.client()
            codes: list[int | None] = []
            for _ in range(2):  # the slave-address register: refused, logged once
                r = await c.write_register(0x03F4, 9, device_id=4)
                codes.append(r.exception_code)
            r = await c.write_register(0x0011, 77, device_id=0)  # a broadcast
            codes.append(r.exception_code if r is not None else None)
            c.close()
            return codes, h.gateway.clients[0], list(h.logs), bus.addresses()["radar-level@4"]

    codes, stats, logs, address = asyncio.run(main())
    assert codes == [1, 1, 0x0A] and stats.refused == 3
    assert address == 4  # the device kept its address
    assert len([x for x in logs if "slave_address" in x]) == 1
    assert len([x for x in logs if "broadcast" in x]) == 1

    async def read_only() -> tuple[int, int]:
        async with served(bus, [("radar-level", 4)], interval=0.2, read_only=True,
                          device_timeout=ANSWERED) as h:
            c = await h.client()
            w = await c.write_register(0x0011, 77, device_id=4)
            r = await c.read_holding_registers(0x0011, count=1, device_id=4)
            c.close()
            return w.exception_code, len(r.registers)

    assert asyncio.run(read_only()) == (1, 1)


def test_a_client_outside_the_allowed_networks_is_closed(sim: Sim) -> None:
    bus = sim("radar-level@4", tick=None)

    async def main() -> tuple[bytes, Any, list[str]]:
        async with served(bus, [], allow=(ipaddress.ip_network("10.0.0.0/8"),)) as h:
            r, w = await asyncio.open_connection("127.0.0.1", h.port)
            w.write(struct.pack(">HHHB", 1, 0, 6, 4) + bytes.fromhex("03 00 00 00 01"))
            got = await end_of(r)
            w.close()
            return got, h.gateway.clients[0], h.logs

    got, stats, logs = asyncio.run(main())
    assert got == b"" and stats.refused == 1
    assert len(logs) == 1 and "not in the allowed networks" in logs[0]


def test_two_clients_at_once_each_get_their_own_answers(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", tick=None)

    async def main() -> list[Any]:
        async with served(bus, [("huiwen-aq", 3), ("radar-level", 4)],
                          device_timeout=ANSWERED) as h:
            a, b = await h.client(), await h.client()

            async def run(c: AsyncModbusTcpClient, unit: int, addr: int, n: int
                          ) -> list[int]:
                out = []
                for _ in range(20):
                    r = (await c.read_input_registers(addr, count=n, device_id=unit)
                         if unit == 3 else
                         await c.read_holding_registers(addr, count=n, device_id=unit))
                    assert not r.isError()
                    out.append(len(r.registers))
                return out

            got = await asyncio.gather(run(a, 3, 0x7536, 5), run(b, 4, 0, 2))
            view = PollView(h.scheduler.buses, title="t", footers=[h.service.footer])
            console = Console(file=io.StringIO(), width=100, color_system=None)
            console.print(view.render())
            a.close()
            b.close()
            snapshot = h.service.snapshot()
            return [*got, console.file.getvalue(), snapshot]  # type: ignore[attr-defined]

    *got, footer, snapshot = asyncio.run(main())
    assert got == [[5] * 20, [2] * 20]
    rows = [line.split() for line in footer.splitlines() if line.startswith("  127.0.0.1:")]
    assert [r[1:3] for r in rows] == [["20", "20"], ["20", "20"]]  # requests, answered
    assert "gateway tcp://127.0.0.1:" in footer and "2 connected" in footer
    clients = snapshot[0]["clients"]
    assert [(c["requests"], c["answered"], c["refused"]) for c in clients] == [(20, 20, 0)] * 2
    assert all(c["wait_p95"] is not None and c["wait_p95"] >= c["wait_p50"] >= 0
               for c in clients)
    assert garbage(bus) == []


def test_a_client_that_leaves_mid_request_costs_nobody_anything(sim: Sim) -> None:
    bus = sim("radar-level@4", "huiwen-aq@3", faults=["4:slow=0.15"], tick=None)

    async def main() -> tuple[int, int, list[int]]:
        async with served(bus, [("huiwen-aq", 3)], interval=0.05, timeout=ANSWERED) as h:
            _r, w = await asyncio.open_connection("127.0.0.1", h.port)
            for tid in range(3):  # three requests to the slow radar, then gone
                w.write(struct.pack(">HHHB", tid, 0, 6, 4) + bytes.fromhex("03 00 00 00 01"))
            await w.drain()
            while not any(f.direction == "in" and f.data[:1] == b"\x04" for f in bus.wire):
                await asyncio.sleep(0.005)  # until the first is on the line (0.05 s of
                # sleep assumed it was, whatever the load)
            w.close()
            await asyncio.sleep(0.3)
            c = await h.client()
            rr = await c.read_holding_registers(0, count=2, device_id=4)
            c.close()
            return h.gateway.pending, h.gateway.clients[0].requests, list(rr.registers)

    pending, requests, regs = asyncio.run(main())
    assert pending == 0 and requests == 3 and len(regs) == 2
    assert garbage(bus) == []
    radar_reads = [w for w in bus.wire if w.direction == "in" and w.data[:1] == b"\x04"]
    assert len(radar_reads) == 2  # the one in flight, then the next client's: none dropped


@pytest.mark.parametrize(("data", "why"), [
    (struct.pack(">HHHB", 1, 0, 9, 4) + bytes.fromhex("03 00 00 00 01 00 00 00"),
     "does not match"),  # wrong length
    (struct.pack(">HHHB", 1, 7, 6, 4) + bytes.fromhex("03 00 00 00 01"), "protocol id 7"),
    (struct.pack(">HHHB", 1, 0, 301, 4) + bytes([3]) + bytes(299), "outside 2..254"),
])
def test_a_malformed_frame_closes_that_client_with_a_log_line(sim: Sim, data: bytes,
                                                              why: str) -> None:
    bus = sim("radar-level@4", tick=None)

    async def main() -> tuple[bytes, list[str], list[int]]:
        async with served(bus, [], timeout=ANSWERED) as h:  # a pure gateway: the line is quiet
            other = await h.client()
            r, w = await asyncio.open_connection("127.0.0.1", h.port)
            w.write(data)
            got = await end_of(r)
            w.close()
            ok = await other.read_holding_registers(0, count=1, device_id=4)
            other.close()
            return got, list(h.logs), list(ok.registers)

    before = len(bus.wire)
    got, logs, regs = asyncio.run(main())
    assert got == b""  # closed, nothing answered
    assert len(logs) == 1 and "malformed frame, connection closed" in logs[0] and why in logs[0]
    assert len(regs) == 1  # the other client is served as before
    assert len([w for w in bus.wire[before:] if w.direction == "in"]) == 1  # only its read


@pytest.mark.timing  # which pipelined request finds the one queue slot free is timing
def test_cache_answers_covered_reads_without_the_line_and_queue_overflow_is_0x0A(
        sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:slow=0.1"], tick=None)

    async def main() -> tuple[int, int, list[bytes]]:
        async with served(bus, [("huiwen-aq", 3)], interval=0.05, cache=5.0, queue=1) as h:
            while not h.readings:
                await asyncio.sleep(0.01)
            c = await h.client()
            for _ in range(5):  # pm25, tvoc, hcho, co2: all polled
                rr = await c.read_input_registers(0x7536, count=4, device_id=3)
                assert rr.registers == list(bus.registers(3, "input", 0x7536, 4))
            rr = await c.read_input_registers(0x7536, count=5, device_id=3)  # 0x753A is not
            assert len(rr.registers) == 5
            c.close()
            stats = h.gateway.clients[0]
            r, w = await asyncio.open_connection("127.0.0.1", h.port)
            for tid in range(4):  # pipelined to the slow radar: its own place and the
                #                   one shared place wait, the other two get 0x0A
                w.write(struct.pack(">HHHB", tid, 0, 6, 4) + bytes.fromhex("03 00 00 00 01"))
            replies = []
            for _ in range(4):
                head = await asyncio.wait_for(r.readexactly(7), 3)
                body = await r.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
                replies.append(body)
            w.close()
            return stats.cached, stats.answered, replies

    cached, answered, replies = asyncio.run(main())
    assert cached == 5 and answered == 6  # the 5-register read went to the line
    assert sorted(body[0] for body in replies) == [0x03, 0x03, 0x83, 0x83]
    assert [body[1] for body in replies if body[0] == 0x83] == [0x0A] * 2
