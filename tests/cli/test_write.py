"""`rtupoll write` against the simulator: the function code each device supports,
read-modify-write of shared registers, read-back, refusals and the confirmation rule."""

from __future__ import annotations

import json
import os
import select
import sys
import time
from collections.abc import Callable
from typing import Any

import conftest
from cli_runner import Ran, rtupoll
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
PATIENT = (*conftest.PATIENT, "--retries", "0")


def run(*args: str, stdin: str | None = None) -> Ran:
    return rtupoll(*args, input=stdin)


def records(result: Ran) -> list[dict[str, Any]]:
    assert result.returncode == 0, (result.stdout + result.stderr)
    return [json.loads(line) for line in result.stdout.splitlines()]


def functions(bus: SimulatedBus) -> list[int]:
    """Function codes of the requests the master sent."""
    return [w.data[1] for w in bus.wire if w.direction == "in"]


def test_banner_write_is_fc16_read_modify_write_keeping_the_other_byte(sim: Sim) -> None:
    bus = sim("banner-ez-array@1", sets=["banner-ez-array@1.measurement_1_mode=FBB",
                                         "banner-ez-array@1.measurement_2_mode=OD"], tick=None)
    before = bus.registers(1, "holding", 40048, 1)[0]
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json",
                       "banner-ez-array@1", "measurement_1_mode=tbb"))
    assert recs[0]["field"] == "measurement_1_mode" and recs[0]["value"] == "TBB"
    after = bus.registers(1, "holding", 40048, 1)[0]
    assert after == (before & 0xFF00) | 3  # high byte (measurement 2 = OD) kept
    assert functions(bus) == [3, 16, 3]  # read current, write (no FC06 on this device), read back


def test_radar_write_uses_fc06_and_scales_the_value(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json",
                       "radar-level@1", "baud_rate=19200"))
    assert recs[0]["value"] == 19200 and recs[0]["raw"] == [192]
    sent = [w.data.hex(" ").upper() for w in bus.wire if w.direction == "in"]
    assert sent[0] == "01 06 03 F6 00 C0 69 EC"


def test_irnet_float_write_uses_fc16_in_its_byte_order(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json",
                       "net-irnet-pro@1", "calibration_gas_level=50"))
    assert recs[0]["value"] == 50.0
    write = next(w.data for w in bus.wire if w.direction == "in" and w.data[1] == 16)
    assert write[7:11] == bytes.fromhex("0000 4842")  # DCBA, as the manual's 50.0 example


def test_write_shows_the_read_back_as_a_table(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("write", "-p", bus.port, *PATIENT, "--yes", "radar-level@1", "baud_rate=9600")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert "after writing (read back)" in result.stdout
    row = next(line for line in result.stdout.splitlines() if "baud_rate" in line)
    assert "9600" in row and "baud" in row


def test_read_only_and_out_of_range_are_refused_before_sending(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", "banner-ez-array@2", tick=None)
    ro = run("write", "-p", bus.port, *PATIENT, "--yes", "huiwen-aq@1", "co2=400")
    big = run("write", "-p", bus.port, *PATIENT, "--yes", "banner-ez-array@2",
              "measurement_1_mode=99")
    bad = run("write", "-p", bus.port, *PATIENT, "--yes", "radar-level@1", "baud_rate=12345")
    assert (ro.returncode, big.returncode, bad.returncode) == (8, 8, 8)
    assert "co2 is read-only" in ro.stderr
    assert "'99' is not one of: DISABLED" in big.stderr
    assert "resolution" in bad.stderr
    assert functions(bus) == []  # nothing went on the wire


def test_the_address_field_is_left_to_set_address(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    result = run("write", "-p", bus.port, *PATIENT, "--yes", "huiwen-aq@1", "slave_address=5")
    assert result.returncode == 8 and "rtupoll set-address huiwen-aq@1 NEW" in result.stderr
    assert functions(bus) == []


def test_without_a_terminal_and_without_yes_nothing_is_written(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("write", "-p", bus.port, *PATIENT, "radar-level@1", "baud_rate=9600")
    assert result.returncode == 8 and "add --yes" in result.stderr
    assert functions(bus) == []


def test_raw_write_with_a_profile_uses_the_function_it_supports(sim: Sim) -> None:
    bus = sim("banner-ez-array@1", tick=None)
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json", "--raw",
                       "banner-ez-array@1", "holding:40048=0x0B03"))
    assert recs[0]["value"] == 0x0B03 and recs[0]["field"] == "holding:40048"
    assert functions(bus) == [16, 3]  # the device has no FC06, even for a raw write
    assert bus.get(1, "measurement_2_mode").value == "OD"


def test_raw_write_of_several_registers_in_one_fc16(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json", "--raw",
                       "net-irnet-pro@1", "holding:0x200=0,0x4842"))
    assert [r["field"] for r in recs] == ["holding:0x0200", "holding:0x0201"]
    assert functions(bus) == [16, 3]
    assert bus.get(1, "calibration_gas_level").value == 50.0  # 00 00 48 42 in DCBA


def test_raw_write_by_modicon_reference_with_no_profile(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    recs = records(run("write", "-p", bus.port, *PATIENT, "--yes", "--format", "json", "--raw",
                       "--modicon", "1", "41015=0x60"))
    assert recs[0]["field"] == "41015" and recs[0]["value"] == 0x60  # wire 0x03F6
    assert functions(bus) == [6, 3]


def test_a_function_the_device_lacks_gets_its_exception_named(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("write", "-p", bus.port, *PATIENT, "--yes", "--raw", "--function", "16", "1",
                 "holding:0x03F6=0x60")
    assert result.returncode == 5 and "ILLEGAL FUNCTION" in result.stderr


def test_raw_write_to_a_read_only_register_gets_the_devices_exception(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("write", "-p", bus.port, *PATIENT, "--yes", "--raw", "1", "holding:0=5")
    assert result.returncode == 5 and "ILLEGAL DATA ADDRESS" in result.stderr


# -- confirmation on a real terminal ----------------------------------------------------


def on_terminal(argv: list[str], answer: str) -> tuple[int, str]:
    """Run ``rtupoll`` on a pty, answer its question, return (exit code, screen)."""
    fd, slave = os.openpty()
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", *argv], stdin=slave, stdout=slave,
                            stderr=slave, close_fds=True)
    os.close(slave)
    screen = b""
    try:
        deadline = time.monotonic() + 30  # (hang guards: the question, the exit end them)
        while b"Send? [y/N]: " not in screen and time.monotonic() < deadline:
            if select.select([fd], [], [], 0.5)[0]:
                screen += os.read(fd, 4096)
        os.write(fd, answer.encode() + b"\n")
        code = proc.wait(timeout=30)
        while select.select([fd], [], [], 0.2)[0]:
            try:
                screen += os.read(fd, 4096)
            except OSError:
                break
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(fd)
    return code, screen.decode(errors="replace")


def test_on_a_terminal_the_change_is_shown_and_only_yes_sends_it(sim: Sim) -> None:
    bus = sim("radar-level@1", sets=["radar-level@1.baud_rate=9600"], tick=None)
    argv = ["write", "-p", bus.port, *PATIENT, "--format", "json", "radar-level@1",
            "baud_rate=19200"]
    code, screen = on_terminal(argv, "n")
    assert code == 8 and "not confirmed: nothing was sent" in screen
    assert "baud_rate = 19200 -> holding 0x03F6 (wire 0x03F6), FC06" in screen
    assert "(now: 9600 baud)" in screen  # what the device holds, read before asking
    assert functions(bus) == [3]  # that read, and no write
    code, screen = on_terminal(argv, "y")
    assert code == 0 and '"value":19200' in screen
    assert functions(bus) == [3, 3, 6, 3]


def test_a_baud_rate_the_device_cannot_run_at_is_refused_before_sending(
        sim: Callable[..., SimulatedBus]) -> None:
    # the read-back would match and the radar would be unreachable after a power cycle
    bus = sim("radar-level@1", tick=None)
    bad = rtupoll("write", "-p", bus.port, "--yes", "radar-level@1",
                  "baud_rate=600")
    assert bad.returncode == 8
    assert bad.stderr == ("rtupoll: baud_rate: 600 is not one of the values it takes: 9600, "
                          "19200, 38400, 57600, 115200\n")
    assert not [f for f in bus.wire if f.direction == "in" and f.data[1] == 6]  # nothing sent
    good = rtupoll("write", "-p", bus.port, "--yes", "--format", "json",
                   "radar-level@1", "baud_rate=19200")
    assert good.returncode == 0, good.stderr
    assert bus.registers(1, "holding", 0x03F6, 1) == (192,)
