"""`rtupoll set-address` against the simulator: every seed device that allows it, the
Huiwen's non-echo reply, the EZ-ARRAY's read-modify-write, every refusal, verification."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest
from cli_runner import Ran, rtupoll

from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
# each silent address probed costs the timeout (wall time, not CPU); an answered one
# ends it, and a loaded machine (load 8 on 2 cores) has answered later than 0.1 s
FAST = ("--timeout", "0.3", "--retries", "0")
# where no write is counted (a late echo would have the write sent again): a live device
# has as long in all (a retry repeats the request, so a late reply answers it), and a
# silent address costs 0.3 s and 0.1 s of drain, not 0.3 s and 0.3 s
RETRIED = ("--timeout", "0.1", "--retries", "2")


def run(*args: str) -> Ran:
    return rtupoll(*args)


def sent(bus: SimulatedBus) -> list[str]:
    return [w.data.hex(" ").upper() for w in bus.wire if w.direction == "in"]


def writes(bus: SimulatedBus) -> list[str]:
    return [h for h in sent(bus) if h.split()[1] in ("06", "10")]


def test_radar_moves_with_fc06_and_is_verified(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("set-address", "-p", bus.port, *FAST, "--yes", "radar-level@1", "11")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert bus.addresses() == {"radar-level@1": 11}
    assert writes(bus) == ["01 06 03 F4 00 0B 89 BB"]
    assert "changed: answers at 11, silent at 1 (write reply: echo)" in result.stdout


@pytest.mark.parametrize("reply", ["short", "none"])
def test_huiwen_non_echo_reply_is_resolved_by_verification(sim: Sim, reply: str) -> None:
    bus = sim("huiwen-aq@1", options=[f"huiwen-aq@1.write_reply={reply}"], tick=None)
    result = run("set-address", "-p", bus.port, *FAST, "--yes", "huiwen-aq@1", "12")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert bus.addresses() == {"huiwen-aq@1": 12}
    assert writes(bus) == ["01 06 9C 41 00 0C F7 8B"]
    assert "(write reply: none or not an echo)" in result.stdout


def test_huiwen_with_a_proper_echo(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "huiwen-aq@1", "0x20")
    assert result.returncode == 0 and bus.addresses() == {"huiwen-aq@1": 32}


def test_banner_fc16_read_modify_write_keeps_the_high_byte_of_41000(sim: Sim) -> None:
    bus = sim("banner-ez-array@1", tick=None)
    (before,) = bus.registers(1, "holding", 41000, 1)
    result = run("set-address", "-p", bus.port, *FAST, "--yes", "banner-ez-array@1", "7")
    assert result.returncode == 0, (result.stdout + result.stderr)
    (after,) = bus.registers(7, "holding", 41000, 1)
    assert after == (before & 0xFF00) | 7 and before & 0xFF00  # a non-zero high byte survived
    (write,) = writes(bus)
    assert write.startswith("01 10 A0 28 00 01 02 ") and write.split()[8] == "07"


def test_json_report_of_one_change(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "--format", "json",
                 "radar-level@1", "11")
    rec = json.loads(result.stdout)
    assert rec == {"row": 1, "profile": "radar-level", "address": 1, "new": 11,
                   "status": "changed", "detail": rec["detail"], "exit_code": 0}


def test_running_it_again_is_recognised_as_done(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    assert run("set-address", "-p", bus.port, *FAST, "--yes", "radar-level@1", "11"
               ).returncode == 0
    again = run("set-address", "-p", bus.port, *FAST, "--yes", "radar-level@1", "11")
    assert again.returncode == 0 and "already done: answers at 11, silent at 1" in again.stdout
    assert len(writes(bus)) == 1


def test_dry_run_prints_the_frames_and_sends_nothing(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    result = run("set-address", "-p", bus.port, "--dry-run", "huiwen-aq@1", "12")
    assert result.returncode == 0
    assert "01 06 9C 41 00 0C F7 8B" in result.stdout and "nothing is sent" in result.stdout
    assert sent(bus) == [] and bus.addresses() == {"huiwen-aq@1": 1}


# -- refusals: exit 8, nothing written ------------------------------------------------


@pytest.mark.parametrize(("device", "new", "why"), [
    ("radar-level@1", "248", "248 is outside this device's range 1..247"),
    ("radar-level@1", "0", "0 is the broadcast address"),
    ("net-irnet-pro@1", "5", "MT-3071 marks register 0x0016 read-only"),
    ("co2meter-an117@254", "5", "set it with CO2Meter's configuration utility"),
])
def test_refused_before_anything_is_sent(sim: Sim, device: str, new: str, why: str) -> None:
    bus = sim(device, tick=None)
    result = run("set-address", "-p", bus.port, *FAST, "--yes", device, new)
    assert result.returncode == 8, (result.stdout + result.stderr)
    assert why in result.stderr and result.stderr.count("\n") == 1
    assert sent(bus) == []


def test_an_address_something_answers_at_is_refused(sim: Sim) -> None:
    bus = sim("radar-level@1", "huiwen-aq@5", tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "radar-level@1", "5")
    assert result.returncode == 8 and "address 5 is taken" in result.stderr
    assert writes(bus) == [] and bus.addresses()["radar-level@1"] == 1


def test_no_device_at_the_old_address_is_exit_4(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "huiwen-aq@1", "12")
    assert result.returncode == 4 and "no device answers at 1" in result.stderr
    assert writes(bus) == []


def test_a_different_kind_of_device_at_the_old_address_is_refused(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "radar-level@1", "12")
    assert result.returncode == 8 and "does not look like a radar-level" in result.stderr
    assert writes(bus) == []


def test_without_a_terminal_it_needs_yes(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("set-address", "-p", bus.port, *FAST, "radar-level@1", "11")
    assert result.returncode == 8 and "--yes" in result.stderr and sent(bus) == []


# -- verification -----------------------------------------------------------------------


def test_a_device_that_vanishes_after_the_write_fails_verification(sim: Sim) -> None:
    # the device's own requests: 1 read at its address, 2 the write; then it goes dead
    bus = sim("radar-level@1", faults=["1:dead@3-"], tick=None)
    result = run("set-address", "-p", bus.port, *RETRIED, "--yes", "radar-level@1", "11")
    assert result.returncode == 6, (result.stdout + result.stderr)
    assert "answers at neither 1 nor 11" in result.stderr


def test_an_address_another_model_reserves_on_the_bus_is_refused(
        sim: Callable[..., SimulatedBus]) -> None:
    # 0xCC is fine for a Huiwen module itself, but CO2Meter boards on the same bus would
    # stop working: refused unless the technician says no such board is there
    bus = sim("huiwen-aq@3", tick=None)
    refused = rtupoll("set-address", "-p", bus.port, *RETRIED, "--yes",
                      "huiwen-aq@3", "0xCC")
    assert refused.returncode == 8
    assert refused.stderr == ("rtupoll: huiwen-aq@3 -> 204: 204 (0xCC) is reserved by "
                              "co2meter-an117 devices (CO2Meter's proprietary protocol uses "
                              "it); --allow-reserved if no such device is on this bus\n")
    assert bus.addresses() == {"huiwen-aq@3": 3}
    allowed = rtupoll("set-address", "-p", bus.port, *RETRIED, "--yes",
                      "--allow-reserved", "huiwen-aq@3", "0xCC")
    assert allowed.returncode == 0, allowed.stderr
    assert bus.addresses() == {"huiwen-aq@3": 204}
