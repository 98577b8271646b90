"""Real clients that no one here wrote read the simulator and get what the profiles say.

mbpoll (libmodbus, run as a subprocess against the pty) and a plain pymodbus client read
every field of every seed device; the words must be the profile's encoding of the
simulated values, and pinned scenario values must come back exactly.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import ANSWERED
from pymodbus import FramerType
from pymodbus.client import AsyncModbusSerialClient, ModbusSerialClient, ModbusTcpClient

from rtupoll.model.interpret import field_words
from rtupoll.model.profile import Field, Poll
from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import DEFAULT_DEVICES, parse_device, profile

Sim = Callable[..., SimulatedBus]

SCENARIO = """\
devices:
  - device: net-irnet-pro@1
    values: {concentration: 412.5, temperature: 296.15, error: NO_ERROR,
             warning: [WARMUP_WARNING], serial_number: AB123456}
  - device: radar-level@2
    values: {air_gap_cm: 321, level_mm: 1790, status: 0}
  - device: huiwen-aq@3
    values: {pm25: 25, tvoc: 0.05, hcho: 0.25, co2: 5000, temperature: -12}
  - device: co2meter-an117@4
    values: {co2: 400}
  - device: banner-ez-array@5
    values: {holding_40001: 555, measurement_1: 17, error_code: 0, outputs: [OUTPUT_2]}
"""
PINS = {
    1: {"concentration": 412.5, "temperature": 296.15, "warning": ["WARMUP_WARNING"],
        "serial_number": "AB123456"},
    2: {"air_gap_cm": 321, "level_mm": 1790},
    3: {"pm25": 25, "tvoc": 0.05, "hcho": 0.25, "co2": 5000, "temperature": -12},
    4: {"co2": 400},
    5: {"holding_40001": 555, "measurement_1": 17, "outputs": ["OUTPUT_2"]},
}
DEVICES = [parse_device(d) for d in DEFAULT_DEVICES]


def readable(pid: str) -> list[Field]:
    """Every register field a client may read (``poll: never`` fields have side effects)."""
    return [f for f in profile(pid).fields if f.poll is not Poll.NEVER and f.table.is_register]


@pytest.fixture
def bus(sim: Sim, tmp_path: Path) -> SimulatedBus:
    path = tmp_path / "scenario.yaml"
    path.write_text(SCENARIO)
    return sim(scenario=path, tick=None)




def mbpoll(port: str, unit: int, f: Field) -> tuple[int, ...]:
    kind = "3" if f.table is Table.INPUT else "4"
    cmd = ["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-0", "-1", "-o", str(ANSWERED),
           "-a", str(unit), "-t", f"{kind}:hex", "-r", str(f.address), "-c", str(f.words), port]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    assert run.returncode == 0, run.stdout[-300:] + run.stderr
    return tuple(int(v, 16) for v in re.findall(r"^\[\d+\]:\s+0x([0-9A-F]{4})", run.stdout,
                                                 re.MULTILINE))


@pytest.mark.parametrize(("pid", "unit"), DEVICES, ids=[d for d, _ in DEVICES])
def test_mbpoll_reads_every_field_as_the_profile_says(bus: SimulatedBus, pid: str,
                                                      unit: int) -> None:
    fields = readable(pid)
    assert fields
    for f in fields:
        words = mbpoll(bus.port, unit, f)
        assert words == bus.registers(unit, f.table, f.address, f.words), f.name
        if f.name in PINS[unit]:
            current = bus.registers(unit, f.table, f.address, f.words)
            assert words == field_words(f, PINS[unit][f.name], current), f.name


def test_mbpoll_sees_exception_02_outside_the_map_and_a_timeout_for_an_absent_id(
        bus: SimulatedBus) -> None:
    base = ["mbpoll", "-m", "rtu", "-P", "none", "-0", "-1", "-t", "3"]
    run = subprocess.run([*base, "-o", str(ANSWERED), "-a", "1", "-r", "16", bus.port],
                         capture_output=True, text=True, timeout=60, check=False)
    assert "Illegal data address" in run.stdout + run.stderr
    run = subprocess.run([*base, "-o", "0.2", "-a", "9", "-r", "6", bus.port],
                         capture_output=True, text=True, timeout=10, check=False)
    assert "timed out" in run.stdout + run.stderr


def _client_read(client: ModbusSerialClient | ModbusTcpClient, unit: int, f: Field
                 ) -> tuple[int, ...]:
    read = client.read_input_registers if f.table is Table.INPUT else \
        client.read_holding_registers
    reply = read(f.address, count=f.words, device_id=unit)
    assert not reply.isError(), (f.name, reply)
    return tuple(reply.registers)


def test_pymodbus_serial_client_reads_every_seed_device(bus: SimulatedBus) -> None:
    client = ModbusSerialClient(bus.port, baudrate=9600, timeout=ANSWERED, retries=0)
    assert client.connect()
    try:
        for pid, unit in DEVICES:
            for f in readable(pid):
                assert _client_read(client, unit, f) == \
                    bus.registers(unit, f.table, f.address, f.words), f"{pid} {f.name}"
        # the CO2Meter's "any sensor" id (mbpoll refuses ids above 247; pymodbus does not)
        assert client.read_input_registers(1, count=1, device_id=0xFE).registers == [400]
    finally:
        client.close()


def test_pymodbus_over_rtu_tcp(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tcp=True, tick=None, sets=["huiwen-aq@3.co2=800"])
    host, _, port = bus.port.removeprefix("tcp://").rpartition(":")
    client = ModbusTcpClient(host, port=int(port), framer=FramerType.RTU, timeout=ANSWERED,
                             retries=0)
    assert client.connect()
    try:
        assert client.read_input_registers(30009, count=1, device_id=3).registers == [800]
    finally:
        client.close()


def test_pymodbus_async_client_and_a_write(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)

    async def main() -> tuple[list[int], list[int]]:
        client = AsyncModbusSerialClient(bus.port, baudrate=9600, timeout=ANSWERED, retries=0)
        await client.connect()
        try:
            await client.write_register(40001, 12, device_id=1)
            moved = await client.read_holding_registers(40001, count=1, device_id=12)
            co2 = await client.read_input_registers(30009, count=1, device_id=12)
            return moved.registers, co2.registers
        finally:
            client.close()

    moved, co2 = asyncio.run(main())
    assert moved == [12]
    assert co2 == list(bus.registers(12, "input", 30009, 1))
    assert bus.addresses() == {"huiwen-aq@1": 12}
