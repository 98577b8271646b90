"""``Gateway.answer``: what each outcome on the line becomes for the client, with a
scripted line (a peer standing in for the bus) instead of a serial port."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

from virtual import heard_nothing

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.site import BusConfig, Site
from rtupoll.errors import DeviceTimeout, FrameError, PortError, RefusedError
from rtupoll.gateway.clients import ClientStats
from rtupoll.gateway.server import Gateway, SilentUnits
from rtupoll.gateway.turns import Turns
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import UnitCounts
from rtupoll.rtu.transaction import ReadResult


class ScriptedLine:
    """Answers each transact with the next outcome: reply bytes or an error to raise."""

    framing = Framing(9600)

    def __init__(self, outcomes: Sequence[bytes | Exception]) -> None:
        self.outcomes = list(outcomes)
        self.sent: list[tuple[int, bytes, float]] = []

    async def open(self) -> None: ...
    async def close(self) -> None: ...

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        raise AssertionError("the gateway reads through transact")

    async def write_registers(self, unit: int, address: int, values: Sequence[int], *,
                              function: int = 16, timeout: float, retries: int = 0,
                              reply: str = "echo") -> bool:
        raise AssertionError("the gateway writes through transact")

    async def write_coil(self, unit: int, address: int, on: bool, *, timeout: float,
                         retries: int = 0) -> None:
        raise AssertionError("the gateway writes through transact")

    adapter_latency = 0.0  # BusLike: no USB adapter
    echo_found = False  # BusLike: no line to hear an echo
    stats = None  # BusLike: counts nothing

    def unit_counts(self, unit: int) -> UnitCounts:
        return heard_nothing(unit)  # nothing measured

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0, idle_gap: float | None = None) -> bytes:
        self.sent.append((unit, pdu, timeout))
        out = self.outcomes.pop(0)
        if isinstance(out, Exception):
            raise out
        return out


def gateway(line: ScriptedLine, **serve: object) -> Gateway:
    site = Site((BusConfig("b", "/dev/null", 9600),))
    bp = Scheduler(site, open_bus=lambda _c: line).buses[0]
    return Gateway(ServeConfig("127.0.0.1", 0, **serve),  # type: ignore[arg-type]
                   bp, Turns())


READ = bytes.fromhex("03 00 10 00 02")


def test_outcomes_on_the_line_become_replies_and_counters() -> None:
    line = ScriptedLine([bytes.fromhex("03 04 00 01 00 02"), bytes.fromhex("83 02"),
                         DeviceTimeout("x"), FrameError("y"), PortError("gone"),
                         RefusedError("cannot build"), b""])
    gw = gateway(line, timeout=0.25)
    st = ClientStats("c")

    async def main() -> list[bytes | None]:
        out = [await gw.answer(7, READ, st) for _ in range(6)]
        out.append(await gw.answer(0, bytes.fromhex("06 00 01 00 05"), st))  # broadcast
        return out

    replies = asyncio.run(main())
    assert replies[:6] == [bytes.fromhex("03 04 00 01 00 02"), bytes.fromhex("83 02"),
                           bytes.fromhex("83 0b"), bytes.fromhex("83 0b"),
                           bytes.fromhex("83 0a"), bytes.fromhex("83 01")]
    assert replies[6] == bytes.fromhex("86 0a")  # broadcasts are not allowed by default
    assert (st.answered, st.exceptions, st.timeouts, st.busy, st.refused) == (1, 1, 2, 1, 2)
    assert [s[2] for s in line.sent] == [0.25] * 6  # an unpolled unit: the default timeout
    assert gw.poller.load.transactions == 6


def test_an_allowed_broadcast_gets_no_reply_and_bad_requests_never_reach_the_line() -> None:
    line = ScriptedLine([b""])
    gw = gateway(line, broadcast=True)
    st = ClientStats("c")

    async def main() -> list[bytes | None]:
        return [await gw.answer(0, bytes.fromhex("06 00 01 00 05"), st),
                await gw.answer(7, bytes.fromhex("03 00 10 00 00"), st),  # 0 registers
                await gw.answer(0, READ, st)]  # a broadcast read

    replies = asyncio.run(main())
    assert replies == [None, bytes.fromhex("83 03"), bytes.fromhex("83 0a")]
    assert [s[0] for s in line.sent] == [0]
    assert st.refused == 2


def test_an_unpolled_unit_that_stopped_answering_is_held_off_in_virtual_time() -> None:
    now = [0.0]
    line = ScriptedLine([DeviceTimeout("x")] * 4 + [bytes.fromhex("03 04 00 01 00 02")])
    site = Site((BusConfig("b", "/dev/null", 9600),))
    bp = Scheduler(site, open_bus=lambda _c: line).buses[0]
    gw = Gateway(ServeConfig("127.0.0.1", 0), bp, Turns(), clock=lambda: now[0])
    st = ClientStats("c")

    def ask(at: float) -> bytes | None:
        now[0] = at
        return asyncio.run(gw.answer(9, READ, st))

    for t in (0.0, 0.1, 0.2):  # three timeouts on the line: then held for 1 s
        assert ask(t) == bytes.fromhex("83 0b")
    assert len(line.sent) == 3
    assert ask(0.9) == bytes.fromhex("83 0b") and len(line.sent) == 3  # at once
    assert ask(1.3) == bytes.fromhex("83 0b") and len(line.sent) == 4  # the probe fails
    assert ask(3.0) == bytes.fromhex("83 0b") and len(line.sent) == 4  # held 2 s now
    assert ask(3.4) == bytes.fromhex("03 04 00 01 00 02")  # the probe is answered
    assert len(line.sent) == 5 and not gw.silent.held(9, 3.5)


def test_counters_as_prometheus_metrics() -> None:
    from prometheus_client import CollectorRegistry, generate_latest

    from rtupoll.gateway.metrics import GatewayCollector
    from rtupoll.gateway.service import GatewayService

    line = ScriptedLine([bytes.fromhex("03 04 00 01 00 02")])
    gw = gateway(line)
    st = ClientStats("127.0.0.1:4000")
    gw.clients.append(st)
    asyncio.run(gw.answer(7, READ, st, queued=gw._clock()))
    service = GatewayService()
    service.gateways.append(gw)
    registry = CollectorRegistry(auto_describe=False)
    registry.register(GatewayCollector(lambda: service.gateways))
    text = generate_latest(registry).decode()
    assert 'rtupoll_gateway_requests_total{bus="b",client="127.0.0.1",' \
        'outcome="answered"} 1.0' in text  # the host: no ephemeral port in a label
    assert 'rtupoll_gateway_clients{bus="b"} 1.0' in text
    assert 'rtupoll_gateway_queue_wait_seconds_count{bus="b",client="127.0.0.1"} 1.0' in text


def test_a_unit_silent_for_days_is_held_at_the_cap() -> None:
    """A client polling a unit nobody answers, for days: the hold stays at the cap (an
    overflowing power would end that client's requests)."""
    silent = SilentUnits(after=3, base=1.0, cap=30.0)
    for _ in range(5000):
        silent.timed_out(9, 0.0)
    assert silent.held(9, 29.9) and not silent.held(9, 30.0)
