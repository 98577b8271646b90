"""The bus against the simulator: every fault kind, wire timing, TCP, and the port itself.

The simulator (``rtupoll.sim``) is an independent RTU peer built from the same
profiles; with ``baudrate`` it delays every frame by its wire time and logs the
wire, so the inter-frame silence is measured on its clock. Port tests cover what a
technician meets first: a port that is missing, busy, gone and back, and a board
that must not see DTR.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, TypeVar

import pytest
import serial
from conftest import ANSWERED, judged

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError, PortError, UsageError
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.rtu import Framing, Table
from rtupoll.sim.runner import SimulatedBus

T = TypeVar("T")
Sim = Callable[..., SimulatedBus]
IRNET_BLOCK = (Table.INPUT, 0x0004, 6)  # temperature .. warning


def run(coro: Coroutine[Any, Any, T]) -> T:
    return asyncio.run(coro)


def image(sim: SimulatedBus, unit: int) -> tuple[int, ...]:
    return sim.registers(unit, IRNET_BLOCK[0], IRNET_BLOCK[1], IRNET_BLOCK[2])


@pytest.mark.parametrize(("fault", "outcome"), [
    ("stray", "ok"), ("stray=255", "ok"), ("wrong-id-first", "ok"),
    ("crc", FrameError), ("truncate", FrameError), ("wrong-id", DeviceTimeout),
    ("exception=6", DeviceException), ("dead", DeviceTimeout), ("slow=0.12", DeviceTimeout),
])
def test_every_fault_kind_while_a_neighbour_stays_right(sim: Sim, fault: str,
                                                        outcome: Any) -> None:
    bus_sim = sim("net-irnet-pro@1", "net-irnet-pro@3", faults=[f"3:{fault}"], tick=None)
    # a device that answers gets all the time a busy machine may need (it costs nothing:
    # the answer ends the wait); one that must time out gets less than the slow one
    # takes; a garbled one is ``judged`` (conftest.py)
    async def ask(bus: Bus) -> Any:
        try:
            if outcome is DeviceTimeout:
                return (await bus.read(3, *IRNET_BLOCK, timeout=0.08)).values
            if outcome is FrameError:
                return (await judged(lambda t: bus.read(3, *IRNET_BLOCK, timeout=t))).values
            return (await bus.read(3, *IRNET_BLOCK, timeout=ANSWERED)).values
        except (DeviceTimeout, FrameError, DeviceException) as exc:
            return type(exc)

    async def go() -> list[Any]:
        got: list[Any] = []
        async with Bus(PortSettings(bus_sim.port, baudrate=115200)) as bus:
            for _ in range(3):
                got.append(await ask(bus))
                got.append((await bus.read(1, *IRNET_BLOCK, timeout=ANSWERED)).values)
        return got
    got = run(go())
    assert got[1::2] == [image(bus_sim, 1)] * 3  # never another request's answer
    if fault.startswith("slow"):  # its own answer, if a busy machine looked only after
        # it came (which answers count as late is exact in virtual time)
        assert set(got[0::2]) <= {DeviceTimeout, image(bus_sim, 3)}, got
    else:
        assert got[0::2] == [image(bus_sim, 3) if outcome == "ok" else outcome] * 3


def test_wire_silence_measured_by_the_simulator(sim: Sim) -> None:
    baud = 9600
    bus_sim = sim("huiwen-aq@3", "co2meter-an117@5", baudrate=baud, tick=None)
    framing = Framing(baud)

    async def go() -> None:
        async with Bus(PortSettings(bus_sim.port, baudrate=baud)) as bus:
            await asyncio.gather(*(bus.read(u, Table.INPUT, a, 1, timeout=ANSWERED)
                                   for u, a in ((3, 30006), (5, 1)) * 5))
    run(go())
    wire = [w for w in bus_sim.wire if w.direction in ("in", "out")]
    assert [w.direction for w in wire] == ["in", "out"] * 10
    gaps = [nxt.time - reply.time for reply, nxt in zip(wire[1::2], wire[2::2], strict=False)]
    assert min(gaps) >= framing.silence
    print(f"achieved silence at {baud} baud: min {min(gaps) * 1e3:.2f} ms, "
          f"max {max(gaps) * 1e3:.2f} ms (t3.5 = {framing.silence * 1e3:.2f} ms)")


def test_rtu_over_tcp_gateway(sim: Sim) -> None:
    """(A gateway reboot is in test_bus.py: the simulator keeps accepted sockets open.)"""
    bus_sim = sim("net-irnet-pro@1", faults=["1:stray@2", "1:wrong-id-first@3"], tcp=True,
                  tick=None)
    assert bus_sim.port.startswith("tcp://")

    async def go() -> list[tuple[int, ...]]:
        async with Bus(PortSettings(bus_sim.port)) as bus:  # (a right reply ends the wait:
            # 0.3 s failed once beside 4 workers under load)
            return [(await bus.read(1, *IRNET_BLOCK, timeout=ANSWERED)).values
                    for _ in range(4)]
    assert run(go()) == [image(bus_sim, 1)] * 4


def test_gateway_refused_and_bad_url() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens once closed

    async def go(url: str) -> None:
        async with Bus(PortSettings(url), connect_timeout=0.5):
            pass
    with pytest.raises(PortError, match=f"gateway 127.0.0.1:{port} refused"):
        run(go(f"tcp://127.0.0.1:{port}"))
    with pytest.raises(UsageError, match="tcp://HOST:PORT"):
        Bus(PortSettings("tcp://nowhere"))


def test_missing_and_busy_port(sim: Sim, tmp_path: Path) -> None:
    async def go(path: str) -> None:
        async with Bus(PortSettings(path)):
            pass
    with pytest.raises(PortError, match="does not exist"):
        run(go(str(tmp_path / "ttyUSB7")))
    bus_sim = sim("co2meter-an117@5")
    holder = serial.serial_for_url(bus_sim.port, exclusive=True)  # another program has it
    try:
        with pytest.raises(PortError, match="busy"):
            run(go(bus_sim.port))
    finally:
        holder.close()
    run(go(bus_sim.port))  # and once it is free, it opens


def test_port_vanishes_and_returns(sim: Sim, tmp_path: Path) -> None:
    """A USB adapter unplugged mid-transaction and plugged back: the process carries on."""
    link = str(tmp_path / "ttyUSB0")
    first = sim("co2meter-an117@5", "co2meter-an117@6", faults=["6:dead"], link=link,
                tick=None)

    async def go() -> list[Any]:
        seen: list[Any] = []
        async with Bus(PortSettings(link, baudrate=115200)) as bus:
            seen.append((await bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)).values)
            # (the loss is noticed when the attempt's time is up, so this 0.5 s is waited
            # out whatever its length: unplugged below as soon as the request is in)
            pending = asyncio.ensure_future(bus.read(6, Table.INPUT, 1, 1, timeout=0.5))
            while not any(w.direction == "in" and w.data[:1] == b"\x06" for w in first.wire):
                await asyncio.sleep(0.005)  # until its request is out (0.05 s of sleep and
                # a 0.2 s timeout: a busy machine unplugged it after the timeout)
            first.stop()  # unplugged while unit 6 is being waited for
            for attempt in (pending, bus.read(5, Table.INPUT, 1, 1, timeout=0.1)):
                try:
                    await attempt
                except (PortError, DeviceTimeout) as exc:
                    seen.append((type(exc), str(exc)))
            second = sim("co2meter-an117@5", link=link, tick=None)  # plugged back
            second.set(5, "co2", 777)
            seen.append((await bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)).values)
            seen.append(bus.stats.outcomes["port"])
        return seen
    seen = run(go())
    assert seen[0] == first.registers(5, Table.INPUT, 1, 1)
    assert seen[1][0] is PortError and "went away" in seen[1][1]
    assert seen[2][0] is PortError and "does not exist" in seen[2][1]
    assert seen[3:] == [(777,), 2]


def test_dtr_and_rts_are_deasserted_before_open(
        sim: Sim, dtr_states: list[tuple[bool, bool]]) -> None:
    """pymodbus opens the port itself; through rtupoll:// it is our Serial that opens it."""
    states = dtr_states
    bus_sim = sim("co2meter-an117@5", tick=None)

    async def go(deassert: bool) -> tuple[int, ...]:
        async with Bus(PortSettings(bus_sim.port, baudrate=115200,
                                    deassert_dtr=deassert)) as bus:
            return (await bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)).values
    run(go(False))
    assert states == [(True, True)]  # rtupoll's Serial too (rtupoll://), lines as pyserial's
    assert run(go(True)) == bus_sim.registers(5, Table.INPUT, 1, 1)
    assert states == [(True, True), (False, False)]


def test_dead_device_costs_its_timeout_not_more(sim: Sim) -> None:
    """Timeouts are per transaction: a dead device costs (retries + 1) x timeout + drain."""
    bus_sim = sim("co2meter-an117@5", "co2meter-an117@6", faults=["6:dead"], tick=None)

    async def go() -> tuple[float, float]:
        async with Bus(PortSettings(bus_sim.port, baudrate=115200)) as bus:
            t = time.monotonic()
            with pytest.raises(DeviceTimeout, match="2 tries"):
                await bus.read(6, Table.INPUT, 1, 1, timeout=0.05, retries=1)
            dead = time.monotonic() - t
            t = time.monotonic()
            await bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)
            return dead, time.monotonic() - t
    dead, live = run(go())
    assert dead >= 0.1  # two attempts of 0.05 s each (and no third)
    assert live >= 0.04  # the drain after the timeout, then the answer (that it answered
    # and did not time out is the read returning; the costs are exact in virtual time,
    # tests/io/test_virtual_bus.py)
