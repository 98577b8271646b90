"""``--traffic`` and ``--capture``: rtupoll's own frames while it works, as log lines and
as a pcapng file that tshark decodes and ``sniff --read`` replays."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import rtupoll

from rtupoll.io import taps
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus
from rtupoll.rtu import with_crc
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
TSHARK = shutil.which("tshark")


def tshark(capture: Path, *fields: str) -> list[list[str]]:
    assert TSHARK is not None, "tshark is not installed (scripts/setup --test installs it)"
    args = [TSHARK, "-r", str(capture), "-T", "fields", "-E", "separator=\t",
            "-d", "rtacser.data,mbrtu", "-o", "mbrtu.crc_verification:TRUE"]
    for f in fields:
        args += ["-e", f]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    return [line.split("\t") for line in proc.stdout.splitlines()]


def test_read_shows_its_request_and_the_reply_in_hex_with_their_meaning(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None, sets=["huiwen-aq@3.co2=800"])
    run = rtupoll("read", "-p", bus.port, "-b", "9600", "--traffic", "huiwen-aq@3", "co2")
    assert run.returncode == 0, run.stderr
    assert "800" in run.stdout  # the table as without --traffic
    sent, heard = run.stderr.splitlines()
    request = ReadRequest(3, 4, 30009, 1).frame().hex(" ").upper()
    assert f"-> {bus.port} {request}  unit 3 read input registers input 30009" in sent
    reply = with_crc(bytes.fromhex("03 04 02 03 20")).hex(" ").upper()
    assert f"<- {bus.port} {reply}  unit 3 read input registers input 30009 = 800" in heard


def test_traffic_as_json_and_a_garbled_reply_shown_as_it_came(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None, faults=["3:crc"])
    run = rtupoll("read", "-p", bus.port, "-b", "9600", "--traffic", "--traffic-format",
                  "json", "--retries", "0", "huiwen-aq@3", "co2")
    assert run.returncode == 7, run.stderr
    records = [json.loads(line) for line in run.stderr.splitlines() if line.startswith("{")]
    assert [r["direction"] for r in records] == ["tx", "rx"]
    assert records[0]["hex"] == ReadRequest(3, 4, 30009, 1).frame().hex(" ").upper()
    assert records[1]["crc_ok"] is False and "CRC ERROR" in records[1]["decoded"]


def test_a_capture_of_poll_on_two_lines_is_decoded_by_tshark_and_replayed(
        tmp_path: Path) -> None:
    capture = tmp_path / "own.pcapng"
    run = rtupoll("poll", "--simulate", "--once", "--format", "json", "--capture",
                  str(capture))
    assert run.returncode == 0, run.stderr
    rows = tshark(capture, "frame.interface_id", "rtacser.eventtype", "mbrtu.unit_id",
                  "modbus.func_code", "_ws.col.Info")
    assert {r[0] for r in rows} == {"0", "1"}  # the demo's two lines, one interface each
    queries = [r for r in rows if r[1] == "0x01"]  # DATA_TX_START: what rtupoll sent
    answers = [r for r in rows if r[1] == "0x02"]
    assert queries and answers
    assert all("Query" in r[4] for r in queries) and any("Response" in r[4] for r in answers)
    assert {r[2] for r in queries} >= {"1", "2", "3", "4", "5"}  # every demo device asked
    replayed = rtupoll("sniff", "--read", str(capture))
    assert replayed.returncode == 0, replayed.stderr
    assert "unit 3" in replayed.stdout and "fc04" in replayed.stdout


@pytest.mark.parametrize("command", [
    ["write", "net-irnet-pro@1", "calibration_gas_level=50", "--yes"],
    ["set-address", "radar-level@2", "12", "--yes"],
    ["scan", "--addresses", "2", "--baudrate", "9600"],
])
def test_every_command_that_talks_to_a_bus_shows_its_traffic(sim: Sim,
                                                             command: list[str]) -> None:
    bus = sim("net-irnet-pro@1", "radar-level@2", tick=None)
    run = rtupoll(command[0], "-p", bus.port, "--traffic", *command[1:])
    assert run.returncode == 0, run.stderr
    lines = [x for x in run.stderr.splitlines() if f" {bus.port} " in x]
    assert any(" -> " in x for x in lines) and any(" <- " in x for x in lines), run.stderr
    if command[0] != "scan":
        assert any("write" in x for x in lines if " -> " in x), run.stderr


def test_without_the_options_the_line_calls_nothing(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    with SyncBus(PortSettings(port=bus.port)) as sync:
        assert sync.line.tap is None
    seen: list[tuple[str, bool, bytes]] = []
    taps.listen(lambda port, framing, sent, data: seen.append((port, sent, data)))
    try:
        with SyncBus(PortSettings(port=bus.port)) as sync:
            assert sync.line.tap is not None
    finally:
        taps.listen(None)
