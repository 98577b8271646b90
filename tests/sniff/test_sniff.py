"""End to end: mbpoll is the master, the simulator the devices, ``rtupoll sniff`` listens
on the simulator's tap (a second pty that hears every byte on the line).

The sniffer must decode what a foreign master reads exactly as the devices hold it,
report faults on the line as faults (never as a value), and a capture written live
must decode offline to the same records.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import pytest
from cli_runner import Ran, rtupoll
from conftest import PATIENT
from forked_cli import rtupoll_popen
from pipe_fill import stall

from rtupoll.model.interpret import interpret
from rtupoll.model.planner import plan
from rtupoll.model.profile import Field, Poll
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import DEFAULT_DEVICES, parse_device, profile

Sim = Callable[..., SimulatedBus]
RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))

SCENARIO = """\
devices:
  - device: net-irnet-pro@1
    values: {concentration: 412.5, temperature: 296.15, error: NO_ERROR,
             warning: [WARMUP_WARNING], serial_number: AB123456}
  - device: radar-level@2
    values: {air_gap_cm: 321, level_mm: 1790, status: 0}
  - device: huiwen-aq@3
    values: {pm25: 25, tvoc: 0.05, hcho: 0.25, co2: 800, temperature: -12}
  - device: co2meter-an117@4
    values: {co2: 400}
  - device: banner-ez-array@5
    values: {holding_40001: 555, measurement_1: 17, error_code: 0, outputs: [OUTPUT_2]}
"""




def readable(pid: str) -> list[Field]:
    return [f for f in profile(pid).fields if f.poll is not Poll.NEVER and f.table.is_register]


def mbpoll(port: str, unit: int, table: Table, address: int, count: int,
           timeout: float = 1.0) -> str:
    kind = "3" if table is Table.INPUT else "4"
    cmd = ["mbpoll", "-m", "rtu", "-b", "9600", "-P", "none", "-0", "-1", "-o", f"{timeout:g}",
           "-a", str(unit), "-t", f"{kind}:hex", "-r", str(address), "-c", str(count), port]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    return run.stdout + run.stderr


@contextmanager
def sniffing(tap: str, *args: str, shown: int = 0) -> Iterator[list[str]]:
    """``rtupoll sniff`` on the tap while the block runs; its stdout lines, as it prints
    them (``printed`` waits for one), all of them afterwards. With ``shown=N`` it is
    stopped only once it has printed N lines (or after a 30 s hang guard): a busy
    machine's sniffer may read the last reply after the block ends."""
    proc = rtupoll_popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None and proc.stdout is not None
    ready = proc.stderr.readline()  # "listening on ..." once the port is open
    assert "listening on" in ready, ready + proc.stderr.read()
    lines: list[str] = []
    done = threading.Event()

    def read(out: IO[str]) -> None:
        for line in out:
            lines.append(line.rstrip("\n"))
            if len(lines) >= shown:
                done.set()
        done.set()

    reader = threading.Thread(target=read, args=(proc.stdout,), daemon=True)
    reader.start()
    try:
        yield lines
    finally:
        if shown:
            done.wait(timeout=30)
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
        reader.join(timeout=30)  # stdout is the reader's alone
        err = proc.stderr.read()
        assert proc.returncode == 0, err


def printed(lines: list[str], text: str) -> None:
    """Wait until the sniffer has printed a line holding ``text`` (a 30 s hang guard)."""
    deadline = time.monotonic() + 30
    while not any(text in line for line in lines):
        assert time.monotonic() < deadline, lines
        time.sleep(0.01)


def records(lines: Sequence[str]) -> list[dict[str, Any]]:
    return [json.loads(line) for line in lines if line.startswith("{")]


@pytest.mark.timing  # the tap frames by real silences: run alone, not beside 6 workers
def test_sniffing_mbpoll_decodes_every_field_of_the_five_seed_devices(
        sim: Sim, tmp_path: Path) -> None:
    scenario = tmp_path / "bus.yaml"
    scenario.write_text(SCENARIO)
    tap, capture = str(tmp_path / "tap"), tmp_path / "line.pcapng"
    bus = sim(scenario=scenario, tick=None, tap=tap)
    devices = list(DEFAULT_DEVICES)
    with sniffing(tap, "--format", "json", "--capture", str(capture), *devices) as lines:
        for spec in devices:
            pid, unit = parse_device(spec)
            # as a master reads them: a block of fields at a time, within the device's
            # limits (one field at a time: 91 mbpoll runs, 2.5 s)
            for b in plan(readable(pid), profile(pid)):
                out = mbpoll(bus.port, unit, b.table, b.address, b.count)
                assert re.search(r"^\[\d+\]:", out, re.MULTILINE), out
    recs = records(lines)
    got = {(r["device"], r["field"]): r for r in recs}
    assert all(r["status"] == "ok" for r in recs), [r for r in recs if r["status"] != "ok"]
    for spec in devices:
        pid, unit = parse_device(spec)
        for f in readable(pid):
            rec = got[spec, f.name]
            truth = interpret(f, bus.registers(unit, f.table, f.address, f.words))
            assert rec["value"] == truth.value, (spec, f.name)
            assert rec["raw"] == list(truth.raw) and rec["profile"] == pid
            assert rec["address"] == unit and rec["unit"] == f.unit
    assert got["huiwen-aq@3", "co2"]["value"] == 800
    assert got["net-irnet-pro@1", "warning"]["value"] == ["WARMUP_WARNING"]
    assert set(recs[0]) == {"time", "device", "profile", "address", "field", "value", "unit",
                            "raw", "severity", "text", "status", "error"}

    # the capture, read back offline, gives the same records
    offline = rtupoll("sniff", "--read", str(capture), "--format", "json", *devices)
    assert offline.returncode == 0, offline.stderr
    assert records(offline.stdout.splitlines()) == recs


@pytest.mark.timing  # a slow reply is told from a late one by the real clock
def test_faults_are_reported_as_faults_and_never_as_values(sim: Sim, tmp_path: Path) -> None:
    tap, capture = str(tmp_path / "tap"), tmp_path / "faults.pcapng"
    bus = sim("huiwen-aq@3", "radar-level@2", "net-irnet-pro@1", tick=None, tap=tap,
              faults=["3:stray=0x00@1", "3:crc@2", "2:slow=0.35@1", "1:dead@1",
                      "1:exception=4@2"])
    co2 = profile("huiwen-aq").field("co2")
    gap = profile("radar-level").field("air_gap_cm")
    conc = profile("net-irnet-pro").field("concentration")
    with sniffing(tap, "--format", "frames", "--timeout", "0.5", "--capture", str(capture),
                  "huiwen-aq@3", "radar-level@2", "net-irnet-pro@1") as lines:
        mbpoll(bus.port, 3, co2.table, co2.address, 1)  # a stray 0x00 before the reply
        mbpoll(bus.port, 3, co2.table, co2.address, 1)  # CRC error
        mbpoll(bus.port, 3, co2.table, co2.address, 1)  # fine
        mbpoll(bus.port, 2, gap.table, gap.address, 1)  # 350 ms late: slow, but answered
        mbpoll(bus.port, 1, conc.table, conc.address, 2, timeout=0.7)  # dead: times out
        # (judged by the sniffer's clock: a starved sniffer that read this request with the
        # next one could not tell, so the next one waits until it has said so)
        printed(lines, "NO REPLY")
        mbpoll(bus.port, 1, conc.table, conc.address, 2)  # exception 04
        mbpoll(bus.port, 1, conc.table, conc.address, 2)  # fine
    text = "\n".join(lines)
    assert "STRAY BYTES: stray bytes 00" in text
    assert "GARBLED REPLY: CRC error in reply" in text
    assert re.search(r"radar-level@2 .* reply 3\d\d\.\d ms SLOW", text), text
    assert "NO REPLY: no reply within 0.5 s" in text
    assert "EXCEPTION: exception 04 SERVER DEVICE FAILURE" in text

    offline = rtupoll("sniff", "--read", str(capture), "--format", "json",
                      "huiwen-aq@3", "radar-level@2", "net-irnet-pro@1")
    assert offline.returncode == 0, offline.stderr
    recs = records(offline.stdout.splitlines())
    statuses = [(r["device"], r["field"], r["status"]) for r in recs]
    assert statuses == [
        ("huiwen-aq@3", "co2", "ok"), ("huiwen-aq@3", "co2", "garbled"),
        ("huiwen-aq@3", "co2", "ok"), ("radar-level@2", "air_gap_cm", "ok"),
        ("net-irnet-pro@1", "concentration", "timeout"),
        ("net-irnet-pro@1", "concentration", "exception"),
        ("net-irnet-pro@1", "concentration", "ok")]
    truth = {("huiwen-aq@3", "co2"): bus.get(3, "co2").value,
             ("radar-level@2", "air_gap_cm"): bus.get(2, "air_gap_cm").value,
             ("net-irnet-pro@1", "concentration"): bus.get(1, "concentration").value}
    for r in recs:
        if r["status"] == "ok":
            assert r["value"] == truth[r["device"], r["field"]]
        else:
            assert r["value"] is None and r["raw"] is None and r["error"]


def test_an_unknown_unit_is_shown_raw_and_looks_like_its_profile(sim: Sim, tmp_path: Path
                                                                   ) -> None:
    tap = str(tmp_path / "tap")
    bus = sim("huiwen-aq@7", tick=None, tap=tap, sets=["huiwen-aq@7.co2=650"])
    p = profile("huiwen-aq")
    with sniffing(tap, "--format", "frames", *PATIENT, shown=2) as lines:
        for name in ("slave_address", "co2"):
            f = p.field(name)
            mbpoll(bus.port, 7, f.table, f.address, f.words)
    text = "\n".join(lines)
    assert "unit 7  fc04 read input 0x7539 x1" in text
    assert "values 028A" in text  # 650, raw: no profile was named
    assert "looks like huiwen-aq" in text


def test_the_sniffer_never_writes_to_the_port(tmp_path: Path) -> None:
    # a pty pair: whatever the sniffer wrote would be readable on the master side
    master, slave = os.openpty()
    try:
        proc = rtupoll_popen([RTUPOLL, "sniff", "-p", os.ttyname(slave), "-b", "9600",
                                 "--format", "frames", "--duration", "0.5"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        proc.communicate(timeout=20)
        assert proc.returncode == 0
        os.set_blocking(master, False)
        try:
            written = os.read(master, 100)
        except BlockingIOError:
            written = b""
        assert written == b""
    finally:
        os.close(master)
        os.close(slave)


def test_a_site_file_names_the_port_the_speed_and_the_devices(sim: Sim, tmp_path: Path
                                                              ) -> None:
    tap = str(tmp_path / "tap")
    bus = sim("huiwen-aq@3", tick=None, tap=tap, sets=["huiwen-aq@3.co2=900"])
    site = tmp_path / "site.yaml"
    site.write_text(f"buses:\n  - name: line1\n    port: {tap}\n    baudrate: 9600\n"
                    "    devices:\n      - {name: air, profile: huiwen-aq, address: 3}\n")
    proc = rtupoll_popen([RTUPOLL, "sniff", "-c", str(site), "--format", "json", *PATIENT],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None and "9600 8N1" in proc.stderr.readline()
    co2 = profile("huiwen-aq").field("co2")
    mbpoll(bus.port, 3, co2.table, co2.address, 1)
    assert proc.stdout is not None
    first = proc.stdout.readline()  # the reading, once the sniffer has read the reply
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    [rec] = records([first, *out.splitlines()])
    assert (rec["device"], rec["field"], rec["value"]) == ("air", "co2", 900)


def rtupoll_run(*args: str) -> Ran:
    """In this process (tests/cli_runner.py), without the RTUPOLL_ variables."""
    return rtupoll(*args, env={k: None for k in os.environ if k.startswith("RTUPOLL_")})


def test_usage_mistakes_are_one_line(tmp_path: Path) -> None:
    for args, code, text in (
            (["sniff"], 2, "give --port"),
            (["sniff", "-p", "/dev/ttyUSB9"], 2, "give --baudrate"),
            (["sniff", "-p", "/dev/nonexistent", "-b", "9600"], 3, "does not exist"),
            (["sniff", "-p", "tcp://127.0.0.1:502", "-b", "9600"], 2, "serial port"),
            (["sniff", "--read", str(tmp_path / "x.pcapng"), "-p", "/dev/ttyUSB0"], 2,
             "leave out --port"),
            (["sniff", "--read", str(tmp_path / "x.pcapng")], 2, "cannot read")):
        proc = rtupoll_run(*args)
        assert proc.returncode == code, (args, proc.stderr)
        assert len(proc.stderr.splitlines()) == 1 and text in proc.stderr, proc.stderr


def test_on_a_terminal_the_default_is_the_live_table(sim: Sim, tmp_path: Path) -> None:
    import pty
    import select
    import time

    tap = str(tmp_path / "tap")
    bus = sim("huiwen-aq@3", tick=None, tap=tap, sets=["huiwen-aq@3.co2=1234"])
    master, slave = pty.openpty()
    # (stopped by Ctrl-C once the value is shown: the duration and the 60 s only guard
    # against a hang; a busy machine took more than 3 s to show it)
    proc = rtupoll_popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", "huiwen-aq@3", *PATIENT,
                             "--duration", "30"], stdin=slave, stdout=slave, stderr=slave)
    out, asked, t0 = b"", False, time.monotonic()
    stopped = False
    try:
        while proc.poll() is None and time.monotonic() - t0 < 60:
            if not asked and b"req/s" in out:  # the table is up: the port is open
                co2 = profile("huiwen-aq").field("co2")
                mbpoll(bus.port, 3, co2.table, co2.address, 1)
                asked = True
            if asked and not stopped and b"1234" in out:  # shown: Ctrl-C, not the duration
                proc.send_signal(signal.SIGINT)
                stopped = True
            if select.select([master], [], [], 0.1)[0]:
                out += os.read(master, 65536)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        os.close(master)
        os.close(slave)
    text = out.decode(errors="replace")
    assert proc.returncode == 0 and asked
    assert "huiwen-aq@3" in text and "1234" in text and "co2" in text


def test_the_simulators_tap_hears_every_byte_in_order(sim: Sim, raw_port: Callable[..., Any],
                                                      tmp_path: Path) -> None:

    bus = sim("huiwen-aq@3", tick=None, tap=str(tmp_path / "tap"))
    assert bus.tap_port.startswith("/dev/pts/")
    tap = raw_port(str(tmp_path / "tap"))
    master = raw_port(bus.port)
    request = ReadRequest(3, 4, 30009, 1).frame()
    reply = master.transact(b"\x55\xaa" + request, 7)
    heard = tap.read(2 + len(request) + len(reply))
    assert heard == b"\x55\xaa" + request + reply


def test_a_stdout_nobody_reads_does_not_stop_ctrl_c(sim: Sim, tmp_path: Path) -> None:
    """``rtupoll sniff ... | consumer`` whose consumer stalls: the lines wait in their
    writer's thread (ui.pipe_writer), so Ctrl-C still ends the sniffer once the pipe is
    full, saying what was not written; the pipe holds whole records."""
    tap = str(tmp_path / "tap")
    bus = sim("huiwen-aq@3", tick=None, tap=tap)
    master = rtupoll_popen([RTUPOLL, "poll", "-p", bus.port, "-b", "9600", "--interval", "0",
                            "--format", "json", "huiwen-aq@3"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    proc = rtupoll_popen([RTUPOLL, "sniff", "-p", tap, "-b", "9600", "--format", "json",
                          "huiwen-aq@3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    try:
        stall(proc, bus)  # nobody reads: the pipe fills, then the queue
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
    finally:
        for p in (proc, master):
            if p.poll() is None:
                p.kill()
            p.wait()
    out, err = proc.stdout.read(), proc.stderr.read().decode()
    assert out.endswith(b"\n") and {json.loads(line)["device"] for line in out.splitlines()
                                    } == {"huiwen-aq@3"}
    assert "bytes not written: nothing read them for 2 s" in err, err
