"""With wire timing the simulated bus answers only at its own baud rate.

(Parity cannot be modelled: Linux pseudo-terminals drop the parity flags.)
"""

from __future__ import annotations

import serial
from conftest import ANSWERED

from rtupoll import rtu
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.runner import simulated_bus

REQUEST = ReadRequest(3, 4, 30006, 1).frame()


def exchange(port: str, baudrate: int, timeout: float = ANSWERED) -> bytes:
    """The reply (its 7 bytes end the wait), or what came within ``timeout``."""
    with serial.Serial(port, baudrate, timeout=timeout) as s:
        s.write(REQUEST)
        return bytes(s.read(7))


def test_answers_at_its_baud_and_is_silent_at_another() -> None:
    with simulated_bus(["huiwen-aq@3"], baudrate=19200, tick=None) as sim:
        assert exchange(sim.port, 9600, timeout=0.3) == b""  # silence: a short wait
        reply = exchange(sim.port, 19200)
        assert rtu.crc_ok(reply) and reply[:3] == bytes([3, 4, 2])
        notes = [f.note for f in sim.wire if f.direction == "in"]
        assert any("another baud rate than the bus's 19200" in n for n in notes)


def test_without_wire_timing_any_baud_is_answered() -> None:
    with simulated_bus(["huiwen-aq@3"], tick=None) as sim:
        assert exchange(sim.port, 4800) != b""
        assert exchange(sim.port, 115200) != b""
