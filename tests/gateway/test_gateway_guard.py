"""The gateway's guard, decided from the function-effect table (``rtupoll.rtu.effects``):
a property test over all 256 function codes, units 0-255 and the guarded registers
drives the real access path (``Gateway.answer``: parse, access, the line) with a
recording line and checks each request that reached it against rules written here
from the standard, independently of the code under test. Named tests for each item of
issue 25 section 1 follow, end to end against the simulator with pymodbus and mbpoll
as the other masters."""

from __future__ import annotations

import asyncio
import functools
import shutil
import struct
import subprocess
from collections.abc import Callable, Sequence
from typing import Any

import pytest
from conftest import ANSWERED
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.site import Site, from_specs
from rtupoll.gateway.clients import ClientStats
from rtupoll.gateway.server import Gateway
from rtupoll.gateway.turns import Turns
from rtupoll.jobs.scheduler import Scheduler
from rtupoll.rtu import Framing, Table
from rtupoll.sim.runner import SimulatedBus
from tests.gateway.test_gateway_sim import served

Sim = Callable[..., SimulatedBus]
MBPOLL = shutil.which("mbpoll")

# the polled devices' address and baud-rate registers (holding), from their profiles
GUARDED = {1: ((22, 23), (124, 125)), 2: ((1012, 1013), (1014, 1015)), 3: ((40001, 40002),)}
# the rules, from the Modbus application protocol, written apart from rtupoll.rtu.effects
HARMLESS_READS = {1, 2, 3, 4, 7, 11, 12, 17, 20, 24}
HARMLESS_DIAGNOSTICS = {0x00, 0x02, *range(0x0B, 0x13)}
STATE_DIAGNOSTICS = {0x01, 0x03, 0x04, 0x0A, 0x14}
BROADCAST_WRITES = {5, 6, 15, 16, 22}


class RecordingLine:
    """A bus that records what reaches it and answers every request the same way."""

    framing = Framing(9600)

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []

    async def open(self) -> None: ...
    async def close(self) -> None: ...

    def late(self, unit: int) -> int:
        return 0

    async def transact(self, unit: int, pdu: bytes, *, timeout: float,
                       retries: int = 0, idle_gap: float | None = None) -> bytes:
        self.sent.append((unit, pdu))
        return b"" if unit == 0 else bytes((pdu[0], 2, 0, 0))


@functools.cache
def site() -> Site:
    """The three devices the rules here are written for (a site is frozen: one will do)."""
    return from_specs("/dev/null", [("net-irnet-pro", 1), ("radar-level", 2),
                                    ("huiwen-aq", 3)], baudrate=9600, check_serial=False)


def gateway(line: RecordingLine, **serve: Any) -> Gateway:
    bp = Scheduler(site(), open_bus=lambda _c: line).buses[0]  # type: ignore[arg-type,return-value]
    return Gateway(ServeConfig("127.0.0.1", 0, **serve), bp, Turns())


def written(pdu: bytes) -> list[tuple[Table, int, int]]:
    """The runs a write request writes, decoded here from the standard's layouts."""
    fc = pdu[0]
    if fc in (5, 6):
        return [(Table.COIL if fc == 5 else Table.HOLDING, int.from_bytes(pdu[1:3], "big"), 1)]
    if fc in (15, 16):
        a, n = struct.unpack_from(">HH", pdu, 1)
        return [(Table.COIL if fc == 15 else Table.HOLDING, a, n)]
    if fc == 22:
        return [(Table.HOLDING, int.from_bytes(pdu[1:3], "big"), 1)]
    if fc == 23:
        _, _, a, n = struct.unpack_from(">HHHH", pdu, 1)
        return [(Table.HOLDING, a, n)]
    raise AssertionError(f"no layout for FC {fc}")


def may_reach_the_line(unit: int, pdu: bytes, cfg: ServeConfig) -> bool:
    """Whether the rules allow ``pdu`` to ``unit`` onto the line at all."""
    fc = pdu[0]
    if unit >= 248:
        return False
    if unit == 0 and not (cfg.broadcast and fc in BROADCAST_WRITES):
        return False
    sub = int.from_bytes(pdu[1:3], "big") if fc == 8 and len(pdu) >= 3 else None
    if cfg.read_only:
        return fc in (1, 2, 3, 4)
    setup = unit in cfg.setup_writes
    if fc == 8:
        return sub in HARMLESS_DIAGNOSTICS or (sub in STATE_DIAGNOSTICS and setup)
    if fc == 43:
        return len(pdu) >= 2 and pdu[1] == 0x0E
    if fc in HARMLESS_READS:
        return True
    if fc not in (5, 6, 15, 16, 21, 22, 23):
        return False
    if setup:
        return True
    if fc == 21:
        return False
    guarded = [g for u, gs in GUARDED.items() if unit in (0, u) for g in gs]
    return not any(t is Table.HOLDING and a < hi and lo < a + n
                   for t, a, n in written(pdu) for lo, hi in guarded)


NEAR = [a + d for runs in GUARDED.values() for lo, _ in runs for a in (lo,) for d in (-2, -1, 0)]
addresses = st.one_of(st.sampled_from(NEAR), st.integers(0, 0xFFFF))
u16 = st.integers(0, 0xFFFF)


@st.composite
def requests(draw: st.DrawFn) -> bytes:
    """Well-formed requests of every kind the guard decides on, and random bytes."""
    kind = draw(st.sampled_from(["random", "read", "single", "multi", "mask", "rw", "diag",
                                 "mei", "short"]))
    if kind == "random":
        return bytes((draw(st.integers(0, 255)),)) + draw(st.binary(max_size=12))
    if kind == "read":
        return struct.pack(">BHH", draw(st.integers(1, 4)), draw(addresses),
                           draw(st.integers(1, 8)))
    if kind == "single":
        fc = draw(st.sampled_from([5, 6]))
        return struct.pack(">BHH", fc, draw(addresses),
                           draw(st.sampled_from([0, 0xFF00])) if fc == 5 else draw(u16))
    if kind == "multi":
        fc = draw(st.sampled_from([15, 16]))
        n = draw(st.integers(1, 6))
        data = draw(st.binary(min_size=(n + 7) // 8 if fc == 15 else 2 * n,
                              max_size=(n + 7) // 8 if fc == 15 else 2 * n))
        return struct.pack(">BHHB", fc, draw(addresses), n, len(data)) + data
    if kind == "mask":
        return struct.pack(">BHHH", 22, draw(addresses), draw(u16), draw(u16))
    if kind == "rw":
        n = draw(st.integers(1, 4))
        return struct.pack(">BHHHHB", 23, draw(addresses), draw(st.integers(1, 8)),
                           draw(addresses), n, 2 * n) + draw(st.binary(min_size=2 * n,
                                                                      max_size=2 * n))
    if kind == "diag":
        return struct.pack(">BHH", 8, draw(st.integers(0, 0x20)), draw(u16))
    if kind == "mei":
        return bytes((43, draw(st.integers(0, 20)), draw(st.integers(1, 4)), 0))
    return bytes((draw(st.sampled_from([7, 11, 12, 17])),))


configs = st.builds(dict, read_only=st.booleans(), broadcast=st.booleans(),
                    setup_writes=st.frozensets(st.sampled_from([1, 2, 3, 9, 250])))
units = st.one_of(st.integers(0, 255), st.sampled_from([0, 1, 2, 3, 248, 254, 255]))


# 200 examples by default (the short profile's 25 are too few for 256 codes x 256 units),
# the long profile's 2,000 on demand; 1,500 every run cost 15 CPU-s
@settings(max_examples=max(200, settings().max_examples), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(configs, units, st.lists(requests(), min_size=1, max_size=4))
def test_nothing_refused_ever_reaches_the_line(cfg: dict[str, Any], unit: int,
                                               pdus: Sequence[bytes]) -> None:
    line = RecordingLine()
    gw = gateway(line, **cfg)
    assert {u: tuple((f.address, f.end) for f in fs) for u, fs in gw.access.guarded.items()
            } == GUARDED  # the profiles this test's rules are written for
    st_ = ClientStats("c")
    for pdu in pdus:
        before = len(line.sent)
        reply = asyncio.run(gw.answer(unit, pdu, st_))
        if len(line.sent) > before:
            assert line.sent[-1] == (unit, pdu)
            assert may_reach_the_line(unit, pdu, gw.config), (unit, pdu.hex(), cfg)
        else:  # refused: an exception to the client (a broadcast has no reply)
            assert reply is not None and reply[0] == pdu[0] | 0x80, (unit, pdu.hex(), cfg)


def test_fc22_and_fc23_to_the_address_register_are_refused_and_the_device_keeps_it(
        sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    mask = struct.pack(">BHHH", 22, 0x9C41, 0x0000, 0x0009)
    rw = struct.pack(">BHHHHBH", 23, 0x9C41, 1, 0x9C41, 1, 2, 9)

    async def main() -> tuple[list[bytes | None], list[bytes | None], list[str]]:
        async with served(bus, [("huiwen-aq", 3)], interval=0.5) as h:
            stats = ClientStats("t")
            to_unit = [await h.gateway.answer(3, p, stats) for p in (mask, rw)]
        async with served(bus, [("huiwen-aq", 3)], interval=0.5, broadcast=True) as h:
            to_all = [await h.gateway.answer(0, p, stats) for p in (mask, rw)]
            return to_unit, to_all, h.logs

    to_unit, to_all, _ = asyncio.run(main())
    assert to_unit == [bytes.fromhex("96 01"), bytes.fromhex("97 01")]
    assert to_all == [bytes.fromhex("96 01"), bytes.fromhex("97 0a")]
    assert bus.addresses()["huiwen-aq@3"] == 3
    assert not [w for w in bus.wire if w.direction == "in" and w.data[1:2] in (b"\x16", b"\x17")]


def test_a_broadcast_fc23_is_refused_even_where_broadcasts_are_allowed() -> None:
    line = RecordingLine()
    gw = gateway(line, broadcast=True)
    rw = struct.pack(">BHHHHBH", 23, 0x0010, 1, 0x0300, 1, 2, 9)  # no guarded register
    st_ = ClientStats("c")
    assert asyncio.run(gw.answer(0, rw, st_)) == bytes.fromhex("97 0a")
    assert asyncio.run(gw.answer(0, struct.pack(">BHH", 6, 0x0300, 9), st_)) is None
    assert line.sent == [(0, struct.pack(">BHH", 6, 0x0300, 9))]


@pytest.mark.parametrize("pdu", [
    pytest.param(struct.pack(">BHH", 8, 0x04, 0), id="fc8-force-listen-only"),
    pytest.param(struct.pack(">BHH", 8, 0x01, 0), id="fc8-restart-communications"),
    pytest.param(struct.pack(">BHH", 8, 0x0A, 0), id="fc8-clear-counters"),
    pytest.param(struct.pack(">BHH", 8, 0x00, 0x1234), id="fc8-echo"),
    pytest.param(bytes((43, 0x0E, 1, 0)), id="fc43-device-id"),
    pytest.param(b"\x11", id="fc17-server-id"), pytest.param(b"\x07", id="fc7"),
    pytest.param(b"\x0b", id="fc11"), pytest.param(struct.pack(">BH", 24, 0), id="fc24"),
    pytest.param(struct.pack(">BHHH", 22, 0x0300, 0, 1), id="fc22"),
])
def test_read_only_refuses_fc8_and_everything_but_reads_of_the_tables(pdu: bytes) -> None:
    line = RecordingLine()
    gw = gateway(line, read_only=True, setup_writes=frozenset({1}))
    st_ = ClientStats("c")
    assert asyncio.run(gw.answer(1, pdu, st_)) == bytes((pdu[0] | 0x80, 1))
    assert asyncio.run(gw.answer(1, bytes.fromhex("03 00 10 00 02"), st_)) == \
        bytes.fromhex("03 02 00 00")
    assert line.sent == [(1, bytes.fromhex("03 00 10 00 02"))]
    assert st_.refused == 1


def test_state_changing_diagnostics_pass_only_to_setup_units() -> None:
    line = RecordingLine()
    gw = gateway(line, setup_writes=frozenset({2}))
    st_ = ClientStats("c")
    listen_only = struct.pack(">BHH", 8, 0x04, 0)
    assert asyncio.run(gw.answer(1, listen_only, st_)) == bytes.fromhex("88 01")
    assert asyncio.run(gw.answer(2, listen_only, st_)) == bytes.fromhex("08 02 00 00")
    assert line.sent == [(2, listen_only)]


@pytest.mark.parametrize("unit", [248, 250, 254, 255])
def test_reserved_units_get_an_exception_and_are_never_forwarded(unit: int) -> None:
    line = RecordingLine()
    gw = gateway(line, setup_writes=frozenset({unit}))
    st_ = ClientStats("c")
    for pdu in (bytes.fromhex("03 00 00 00 01"), bytes.fromhex("06 00 16 00 05")):
        assert asyncio.run(gw.answer(unit, pdu, st_)) == bytes((pdu[0] | 0x80, 0x0A))
    assert line.sent == []


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed (scripts/setup installs it)")
def test_mbpoll_asking_unit_255_gets_an_exception_and_the_line_never_sees_it(sim: Sim
                                                                               ) -> None:
    bus = sim("huiwen-aq@3", tick=None)

    async def main() -> tuple[subprocess.CompletedProcess[str], list[str]]:
        async with served(bus, [("huiwen-aq", 3)], interval=0.5) as h:
            assert MBPOLL is not None
            done = await asyncio.to_thread(
                subprocess.run, [MBPOLL, "-m", "tcp", "-p", str(h.port), "-1",
                                 "-o", f"{ANSWERED:g}", "-a", "255", "-t", "4", "-r", "1",
                                 "127.0.0.1"],
                capture_output=True, text=True, timeout=60)  # (the exception ends its wait)
            return done, h.logs

    done, logs = asyncio.run(main())
    assert done.returncode != 0
    assert "Gateway path unavailable" in done.stdout + done.stderr or \
        "0x0a" in (done.stdout + done.stderr).lower(), done.stdout + done.stderr
    assert any("unit 255 is reserved" in x for x in logs), (logs, done.stdout)
    assert not [w for w in bus.wire if w.direction == "in" and w.data[:1] == b"\xff"]
