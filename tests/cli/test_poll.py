"""``rtupoll poll``: one-shot scans, output formats, site files, the simulator, and errors.

These run the real command in-process (``cli_runner.rtupoll``: the console script's
entry point, which maps errors to exit codes) against simulated buses. Streaming under faults
and signals is in ``test_poll_faults.py``.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import serial
from cli_runner import Ran, rtupoll
from conftest import ANSWERED, PATIENT, live_and_dead

from rtupoll.model.record import POLL_KEYS
from rtupoll.sim.runner import SimulatedBus


def poll(*args: str) -> Ran:
    return rtupoll("poll", *args)


def records(result: Ran) -> list[dict[str, Any]]:
    return [json.loads(line) for line in result.stdout.splitlines()]


def test_once_json_gives_one_record_per_field_with_the_poll_keys(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4")
    bus.set(3, "co2", 777)
    bus.set(4, "air_gap_cm", 123)
    result = poll("--port", bus.port, "--once", "--format", "json", *PATIENT, "huiwen-aq@3",
                  "radar-level@4")
    assert result.returncode == 0, result.stderr
    recs = records(result)
    assert all(tuple(r) == POLL_KEYS for r in recs)
    assert [(r["device"], r["field"]) for r in recs][:2] == [("huiwen-aq@3", "pm25"),
                                                             ("huiwen-aq@3", "tvoc")]
    by = {(r["address"], r["field"]): r for r in recs}
    assert len(by) == 15 + 5
    assert by[3, "co2"]["value"] == 777 and by[3, "co2"]["unit"] == "ppm"
    assert by[4, "air_gap_cm"]["value"] == 123
    assert {r["status"] for r in recs} == {"ok"} and {r["error"] for r in recs} == {""}
    assert all(r["time"].endswith("Z") and r["time"][10] == "T" for r in recs)


def test_once_with_a_dead_device_names_it_and_exits_9(sim: Callable[..., SimulatedBus],
                                                      tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:dead"])
    result = poll("--config", str(live_and_dead(tmp_path, bus.port)), "--once", "--format",
                  "json")
    assert result.returncode == 9
    assert result.stderr.splitlines() == [
        "rtupoll: radar-level@4: timeout: no reply from unit 4 to read holding registers "
        "within 0.1 s (2 tries) (5 of 5 fields not read)",
        "rtupoll: 1 of 2 devices failed",
    ]
    failed = [r for r in records(result) if r["address"] == 4]
    assert [r["status"] for r in failed] == ["timeout", "skipped", "skipped", "skipped",
                                             "skipped"]
    assert all(r["value"] is None and r["severity"] == "error" for r in failed)
    assert all(r["status"] == "ok" for r in records(result) if r["address"] == 3)


def test_once_exception_and_garbled_replies_are_each_one_line(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["3:exception=2", "4:crc"])
    # (both answer, known as the answers come: not asked within a short timeout)
    result = poll("--port", bus.port, "--once", *PATIENT, "huiwen-aq@3",
                  "radar-level@4")
    assert result.returncode == 9
    lines = result.stderr.splitlines()
    assert len(lines) == 3 and lines[-1] == "rtupoll: 2 of 2 devices failed"
    assert lines[0].startswith("rtupoll: huiwen-aq@3: exception: device 3 answered to "
                               "function 0x04 with exception 02 ILLEGAL DATA ADDRESS")
    assert lines[1].startswith("rtupoll: radar-level@4: garbled: unit 4, read holding "
                               "registers: ")
    assert "CRC" in lines[1]


def test_once_table_shows_names_of_enums_flags_and_unknown_codes(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("net-irnet-pro@1", "huiwen-aq@3", "radar-level@4")
    bus.set(1, "warning", ["WARMUP_WARNING", "INVALID_READINGS_WARNING"])
    bus.set(1, "error", "LAMP_ERROR")
    bus.set(3, "co2_level", "MODERATE")
    bus.set(3, "pm25_level", 9)  # not in the manual's table
    bus.set(4, "status", 7)  # the profile's 'other' code
    result = rtupoll("poll", "--port", bus.port, "--baudrate", "9600", "--once", *PATIENT,
                     "net-irnet-pro@1", "huiwen-aq@3", "radar-level@4", env={"COLUMNS": "160"})
    assert result.returncode == 0, result.stderr
    rows = {tuple(line.split()[:1] + line.split()[-3:]) for line in result.stdout.splitlines()}
    text = result.stdout
    assert "WARMUP_WARNING, INVALID_READINGS_WARNING" in text
    # the reading's severity and the transaction's status, apart (as in JSON)
    cells = [[c.strip() for c in line.split("│")] for line in text.splitlines()]
    assert any(c[2:] == ["LAMP_ERROR", "", "error", "ok"] for c in cells)
    assert any(c[2:] == ["MODERATE", "", "warning", "ok"] for c in cells)
    assert any("unknown (9)" in line and "unknown code" in line for line in text.splitlines())
    assert any("MEASUREMENT_ERROR (7)" in line for line in text.splitlines())
    # the health footer: each device online, with its counters
    assert any(line.split()[:2] == ["huiwen-aq@3", "online"] for line in text.splitlines())
    assert rows  # the table was printed


def test_csv_to_a_file_appends_with_one_header(sim: Callable[..., SimulatedBus],
                                              tmp_path: Path) -> None:
    bus = sim("radar-level@4")
    out = tmp_path / "readings.csv"
    for _ in range(2):
        result = poll("--port", bus.port, "--once", "--format", "csv", "--output", str(out),
                      *PATIENT, "radar-level@4")
        assert result.returncode == 0, result.stderr
        assert result.stdout == ""
    rows = list(csv.DictReader(io.StringIO(out.read_text())))
    assert len(rows) == 10 and tuple(rows[0]) == POLL_KEYS
    assert [r["field"] for r in rows[:5]] == ["air_gap_cm", "air_gap_mm", "level_cm",
                                              "level_mm", "status"]
    assert out.read_text().count("time,device") == 1


def test_a_site_file_polls_several_buses_concurrently(sim: Callable[..., SimulatedBus],
                                                      tmp_path: Path) -> None:
    north, south = sim("huiwen-aq@3"), sim("radar-level@4", "radar-level@5")
    north.set(3, "co2", 555)
    south.set(5, "air_gap_cm", 42)
    site = tmp_path / "site.yaml"
    site.write_text(f"""\
buses:
  - name: north
    port: {north.port}
    devices:
      - {{name: air, profile: huiwen-aq, address: 3, fields: [co2, temperature]}}
  - name: south
    port: {south.port}
    devices:
      - {{name: tank-a, profile: radar-level, address: 4}}
      - {{name: tank-b, profile: radar-level, address: 5, fields: [air_gap_cm]}}
""")
    result = poll("--config", str(site), "--once", "--format", "json")
    assert result.returncode == 0, result.stderr
    recs = records(result)
    assert [(r["device"], r["field"]) for r in recs] == [
        ("air", "co2"), ("air", "temperature"),
        ("tank-a", "air_gap_cm"), ("tank-a", "air_gap_mm"), ("tank-a", "level_cm"),
        ("tank-a", "level_mm"), ("tank-a", "status"), ("tank-b", "air_gap_cm")]
    assert recs[0]["value"] == 555 and recs[-1]["value"] == 42


def test_simulate_once_reads_the_five_seed_devices() -> None:
    result = poll("--simulate", "--once", "--format", "json", *PATIENT)
    assert result.returncode == 0, result.stderr
    profiles = {r["profile"] for r in records(result)}
    assert profiles == {"net-irnet-pro", "radar-level", "huiwen-aq", "co2meter-an117",
                        "banner-ez-array"}
    assert {r["status"] for r in records(result)} == {"ok"}


def test_simulate_with_a_fault_reports_that_device() -> None:
    result = poll("--simulate", "--once", "--fault", "3:dead", "--format", "json")
    assert result.returncode == 9
    assert result.stderr.splitlines()[0].startswith("rtupoll: huiwen-aq@3: timeout: ")
    assert result.stderr.splitlines()[-1] == "rtupoll: 1 of 5 devices failed"


def test_a_missing_port_is_exit_3_in_one_line() -> None:
    result = poll("--port", "/dev/ttyNOPE0", "--once", "radar-level@1")
    assert result.returncode == 3
    assert len(result.stderr.splitlines()) == 1
    assert result.stderr.startswith("rtupoll: ") and "/dev/ttyNOPE0" in result.stderr
    assert "Traceback" not in result.stderr


def test_a_busy_port_is_exit_3_in_one_line(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("radar-level@1")
    with serial.Serial(bus.port, exclusive=True):
        result = poll("--port", bus.port, "--once", "radar-level@1")
    assert result.returncode == 3
    assert len(result.stderr.splitlines()) == 1 and "busy" in result.stderr


def test_usage_mistakes_are_exit_2() -> None:
    cases = {
        ("--port", "/dev/null", "--output", "x.json", "radar-level@1"):
            "rtupoll: --output writes json or csv: add --format json or --format csv",
        ("--config", "site.yaml", "--port", "/dev/null"):
            "rtupoll: give either --config or --port with devices, not both",
        ():
            "rtupoll: nothing to poll: give --config FILE, or --port PORT and DEVICEs "
            "(PROFILE@ADDRESS), or --simulate to try it without hardware",
        ("--port", "/dev/null"):
            "rtupoll: name the devices on /dev/null: PROFILE@ADDRESS... (e.g. net-irnet-pro@1), "
            "or --serve HOST:PORT to be a gateway",
        ("--port", "/dev/null", "--baud", "9600", "radar-level@1"):
            "rtupoll: --baud and --fault are for --simulate (a real bus: --baudrate)",
        ("--port", "/dev/null", "nope@1"):
            "rtupoll: no profile 'nope'; see 'rtupoll profiles list'",
    }
    for args, message in cases.items():
        result = poll(*args)
        assert (result.returncode, result.stderr.strip()) == (2, message), args


def test_fields_a_devices_variant_lacks_are_reported_absent_not_failed(
        sim: Callable[..., SimulatedBus]) -> None:
    # an IRNET-PRO on data structure 0 has no calibration gas level (exception 02 there)
    bus = sim("net-irnet-pro@1", "net-irnet-pro@2", options=["net-irnet-pro@1.variant=0"])
    bus.set(2, "calibration_gas_level", 50.0)
    result = poll("--port", bus.port, "--once", "--format", "json", *PATIENT, "--fields",
                  "concentration,calibration_gas_level", "net-irnet-pro@1", "net-irnet-pro@2")
    assert result.returncode == 0, result.stderr
    by = {(r["address"], r["field"]): r for r in records(result)}
    old = by[1, "calibration_gas_level"]
    assert (old["status"], old["value"], old["error"], old["severity"]) == (
        "absent", None, "not in data structure 0", "info")
    assert by[1, "concentration"]["status"] == "ok"
    assert by[2, "calibration_gas_level"]["value"] == 50.0
    # the probe read input 0x0400 once per device; no request touched 0x0200 on unit 1
    asked = [f.data for f in bus.wire if f.direction == "in"]
    assert not any(a[0] == 1 and a[1] == 3 and a[2:4] == b"\x02\x00" for a in asked)


def test_a_device_whose_every_asked_field_is_absent_stays_online(
        sim: Callable[..., SimulatedBus]) -> None:
    import asyncio

    from rtupoll.config.site import from_specs
    from rtupoll.jobs.scheduler import Scheduler

    bus = sim("net-irnet-pro@1", options=["net-irnet-pro@1.variant=0"])
    site = from_specs(bus.port, [("net-irnet-pro", 1)], fields=["uart_speed"], interval=0,
                      timeout=ANSWERED)

    async def three_scans() -> tuple[str, int, int]:
        scheduler = Scheduler(site)
        await scheduler.open()
        try:
            for _ in range(3):
                await scheduler.scan_once(lambda d, rs: None)
            st = scheduler.pollers()[0].stats
            return st.state.value, st.failures, st.requests
        finally:
            await scheduler.close()
    # one probe learns data structure 0; nothing else is ever sent, and it is no failure
    assert asyncio.run(three_scans()) == ("online", 0, 1)


def test_an_even_parity_device_polls_on_the_simulators_pty() -> None:
    """The ABB B23 runs 8E1; a pty has no parity bit (and Linux refuses to set one on
    it after its first open), so the simulator's port is opened without one."""
    for _ in range(2):  # the second open is the one Linux refused
        result = poll("--simulate", "abb-b23@1", "--once", "--format", "json", *PATIENT)
        assert result.returncode == 0, (result.stdout + result.stderr)
        assert all(r["status"] == "ok" for r in records(result))
