"""A capture ``rtupoll sniff --capture`` wrote, decoded by Wireshark's ``tshark`` as
docs/sniff.md prints it (``-d rtacser.data,mbrtu``): every request and reply is Modbus
RTU with a good CRC, with the units, functions, addresses and register values that were
on the line (the simulator's registers, read by mbpoll as the foreign master).
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import profile
from tests.sniff.test_sniff import mbpoll, sniffing

TSHARK = shutil.which("tshark") or "/usr/bin/tshark"
FIELDS = ("frame.number", "mbrtu.unit_id", "modbus.func_code", "modbus.reference_num",
          "modbus.word_cnt", "modbus.regval_uint16", "mbrtu.crc16.status")


def tshark(capture: Path, *args: str) -> list[list[str]]:
    if not Path(TSHARK).exists():
        pytest.fail("tshark is not installed (Debian: apt-get install tshark)")
    run = subprocess.run([TSHARK, "-r", str(capture), *args], capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0, run.stderr
    return [line.split("\t") for line in run.stdout.splitlines()]


# the capture holds what each read of the tap brought: a frame a packet only while the
# sniffer reads each frame before the next one starts (a reply and mbpoll's next request
# came as one packet beside 8 busy workers)
@pytest.mark.timing
def test_tshark_decodes_an_rtupoll_capture_as_modbus_rtu(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    tap, capture = str(tmp_path / "tap"), tmp_path / "line.pcapng"
    # wire timing, and 0.2 s between request and reply: each frame is a chunk of its own
    bus = sim("huiwen-aq@3", "radar-level@2", tick=None, tap=tap, baudrate=9600, turnaround=0.2)
    bus.set(3, "co2", 812)
    co2 = profile("huiwen-aq").field("co2")
    gap = profile("radar-level").field("air_gap_cm")
    asks = [(3, co2.table, co2.address, 1), (2, gap.table, gap.address, 1)]
    outs: list[str] = []
    with sniffing(tap, "--format", "frames", "--capture", str(capture), "huiwen-aq@3"):
        for unit, table, address, count in asks:
            out = mbpoll(bus.port, unit, table, address, count)
            outs.append(out)
            assert "[" in out, out
    assert capture.stat().st_size > 0

    # without the Decode As, tshark sees the link type only: RTAC Serial
    plain = tshark(capture, "-T", "fields", "-e", "frame.protocols")
    assert plain and all(row[0].startswith("rtacser") and "mbrtu" not in row[0]
                         for row in plain), plain

    rows = tshark(capture, "-d", "rtacser.data,mbrtu", "-T", "fields",
                  *(x for f in FIELDS for x in ("-e", f)))
    frames = [dict(zip(FIELDS, row, strict=True)) for row in rows]
    assert len(frames) == 2 * len(asks), (rows, outs)  # a request and a reply each, no split frame
    for (unit, table, address, count), request, reply in zip(
            asks, frames[0::2], frames[1::2], strict=True):
        fc = "4" if table is Table.INPUT else "3"
        assert (request["mbrtu.unit_id"], request["modbus.func_code"]) == (str(unit), fc)
        assert (request["modbus.reference_num"], request["modbus.word_cnt"]) == (
            str(address), str(count))
        assert (reply["mbrtu.unit_id"], reply["modbus.func_code"]) == (str(unit), fc)
        truth = bus.registers(unit, table, address, count)
        assert reply["modbus.regval_uint16"] == ",".join(str(w) for w in truth)
        assert request["mbrtu.crc16.status"] == reply["mbrtu.crc16.status"] == "2"  # good
    assert frames[1]["modbus.regval_uint16"] == "812"
