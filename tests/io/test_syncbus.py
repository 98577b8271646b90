"""The blocking bus (``rtupoll.io.syncbus``) against the simulator: the same transaction
as the async bus, driven without an event loop (what ``rtupoll read`` uses).

The simulator is the independent RTU peer; with ``baudrate`` it logs the wire on its
own clock, so the inter-frame silence is measured there, not by the bus under test.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

import pytest
import serial
from conftest import ANSWERED

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError, PortError
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus, run
from rtupoll.jobs.device import read_fields
from rtupoll.rtu import Framing, Table
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
IRNET_BLOCK = (Table.INPUT, 0x0004, 6)  # temperature .. warning


def image(sim: SimulatedBus, unit: int) -> tuple[int, ...]:
    return sim.registers(unit, *IRNET_BLOCK)


@pytest.mark.parametrize(("fault", "outcome"), [
    ("stray", "ok"), ("wrong-id-first", "ok"), ("crc", FrameError),
    ("exception=6", DeviceException), ("dead", DeviceTimeout),
])
def test_faults_while_a_neighbour_stays_right(sim: Sim, fault: str, outcome: Any) -> None:
    bus_sim = sim("net-irnet-pro@1", "net-irnet-pro@3", faults=[f"3:{fault}"], tick=None)
    patience = 0.08 if outcome is DeviceTimeout else ANSWERED  # (crc: known as it comes)
    got: list[Any] = []
    with SyncBus(PortSettings(bus_sim.port, baudrate=115200)) as bus:
        for _ in range(3):
            try:
                got.append(run(bus.read(3, *IRNET_BLOCK, timeout=patience)).values)
            except (DeviceTimeout, FrameError, DeviceException) as exc:
                got.append(type(exc))
            got.append(run(bus.read(1, *IRNET_BLOCK, timeout=ANSWERED)).values)
        stats = bus.stats
    assert got[1::2] == [image(bus_sim, 1)] * 3  # never another request's answer
    assert got[0::2] == [image(bus_sim, 3) if outcome == "ok" else outcome] * 3
    assert stats.transactions == 6
    assert stats.outcomes["ok"] == 3 + (3 if outcome == "ok" else 0)


def test_wire_silence_measured_by_the_simulator(sim: Sim) -> None:
    baud = 9600
    bus_sim = sim("huiwen-aq@3", "co2meter-an117@5", baudrate=baud, tick=None)
    with SyncBus(PortSettings(bus_sim.port, baudrate=baud)) as bus:
        for unit, address in ((3, 30006), (5, 1)) * 5:
            run(bus.read(unit, Table.INPUT, address, 1, timeout=ANSWERED))
    wire = [w for w in bus_sim.wire if w.direction in ("in", "out")]
    assert [w.direction for w in wire] == ["in", "out"] * 10
    gaps = [nxt.time - reply.time for reply, nxt in zip(wire[1::2], wire[2::2], strict=False)]
    assert min(gaps) >= Framing(baud).silence


def test_the_planner_and_the_holes_run_on_it_unchanged(sim: Sim) -> None:
    """The jobs written for any bus (coroutines awaiting only the bus) run to the end."""
    bus_sim = sim("huiwen-aq@1", sets=["huiwen-aq@1.co2=612"], tick=None)
    from rtupoll.config.library import load_one

    profile = load_one("huiwen-aq")
    with SyncBus(PortSettings(bus_sim.port)) as bus:
        got = run(read_fields(bus, profile, 1, [profile.field("co2")], timeout=ANSWERED,
                              retries=0, probe=True))
    assert got.refused == () and [(v.field.name, v.value) for v in got.values] == [("co2", 612)]


def test_a_job_that_awaits_anything_else_is_refused() -> None:
    class Elsewhere:
        def __await__(self) -> Generator[None, None, int]:
            yield None  # as an event loop's future would
            return 1

    async def job() -> int:
        return await Elsewhere()

    with pytest.raises(RuntimeError, match="awaited something else"):
        run(job())


def test_rtu_over_tcp_gateway(sim: Sim) -> None:
    bus_sim = sim("net-irnet-pro@1", faults=["1:stray@2", "1:wrong-id-first@3"], tcp=True,
                  tick=None)
    with SyncBus(PortSettings(bus_sim.port)) as bus:
        got = [run(bus.read(1, *IRNET_BLOCK, timeout=ANSWERED)).values for _ in range(4)]
    assert got == [image(bus_sim, 1)] * 4


def test_gateway_refused() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens once closed
    with pytest.raises(PortError, match=f"gateway 127.0.0.1:{port} refused"), \
            SyncBus(PortSettings(f"tcp://127.0.0.1:{port}"), connect_timeout=0.5):
        pass


def test_missing_and_busy_port(sim: Sim, tmp_path: Path) -> None:
    with pytest.raises(PortError, match="does not exist"), \
            SyncBus(PortSettings(str(tmp_path / "ttyUSB7"))):
        pass
    bus_sim = sim("co2meter-an117@5")
    holder = serial.serial_for_url(bus_sim.port, exclusive=True)  # another program has it
    try:
        with pytest.raises(PortError, match="busy"), SyncBus(PortSettings(bus_sim.port)):
            pass
    finally:
        holder.close()
    with SyncBus(PortSettings(bus_sim.port)) as bus:  # once it is free, it opens
        assert bus.connected


def test_a_port_that_goes_away_mid_transaction(sim: Sim, tmp_path: Path) -> None:
    link = str(tmp_path / "ttyUSB0")
    bus_sim = sim("co2meter-an117@5", faults=["5:slow=30"], link=link, tick=None)
    with SyncBus(PortSettings(link, baudrate=115200)) as bus:
        import threading

        def unplug() -> None:  # once the request is in: unplugged while the reply is awaited
            bus_sim.wait_wire(1, direction="in", timeout=30)
            bus_sim.stop()
        threading.Thread(target=unplug, daemon=True).start()
        with pytest.raises(PortError, match="went away"):  # (the reply is 30 s away; the
            # port going away ends the wait, however late a busy machine unplugs it)
            run(bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED))
        assert bus.stats.outcomes["port"] == 1 and not bus.connected


def test_dtr_and_rts_are_deasserted_before_open(
        sim: Sim, dtr_states: list[tuple[bool, bool]]) -> None:
    states = dtr_states
    bus_sim = sim("co2meter-an117@5", tick=None)
    with SyncBus(PortSettings(bus_sim.port, baudrate=115200, deassert_dtr=True)) as bus:
        assert run(bus.read(5, Table.INPUT, 1, 1, timeout=ANSWERED)).values == \
            bus_sim.registers(5, Table.INPUT, 1, 1)
    assert states == [(False, False)]


def test_a_dead_device_costs_its_timeouts(sim: Sim) -> None:
    bus_sim = sim("co2meter-an117@5", "co2meter-an117@6", faults=["6:dead"], tick=None)
    with SyncBus(PortSettings(bus_sim.port, baudrate=115200)) as bus:
        t = time.monotonic()
        with pytest.raises(DeviceTimeout, match="2 tries"):
            run(bus.read(6, Table.INPUT, 1, 1, timeout=0.05, retries=1))
        assert time.monotonic() - t >= 0.1
        assert (bus.stats.attempts, bus.stats.retries) == (2, 1)
