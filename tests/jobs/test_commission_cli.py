"""Commissioning runs: a plan that fails half-way and is re-run to completion, the JSON
report, and the interactive field workflow driven through a real pseudo-terminal."""

from __future__ import annotations

import json
import os
import select
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

from cli_runner import Ran, rtupoll
from forked_cli import rtupoll_popen

from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
# each silent address probed costs the timeout three times, and its drain; a live device
# that answers late (a busy machine's simulator thread answered later than 0.1 s, and at
# load 10 later than 0.2 s: "no device answers at 1") has its late reply taken as a
# retry's answer (a retry repeats the request): 0.3 s in all, as tests/cli/test_address.py's
# one 0.3 s timeout (whose drain costs 0.3 s more)
FAST = ("--timeout", "0.1", "--retries", "2")
PLAN = Path(__file__).parents[1] / "fixtures" / "commission" / "three.csv"


def run(*args: str) -> Ran:
    return rtupoll(*args)


def three(sim: Sim) -> SimulatedBus:
    """The plan's bus; the Huiwen at 2 reports a sensor fault, so its identity check fails."""
    return sim("radar-level@1", "huiwen-aq@2", "banner-ez-array@3", tick=None,
               sets=["huiwen-aq@2.co2_failure=COMMUNICATION_FAULT"])


def test_a_plan_that_fails_half_way_is_rerun_to_completion(sim: Sim) -> None:
    bus = three(sim)
    first = run("set-address", "-p", bus.port, *FAST, "-b", "9600", "--yes", "--plan", str(PLAN))
    assert first.returncode == 8, first.stderr
    lines = first.stdout.splitlines()
    assert lines[0].startswith("ok   radar-level@1 -> 11: changed")
    assert lines[1].startswith("FAIL huiwen-aq@2 -> 12: ")
    assert "co2_failure reads 'COMMUNICATION_FAULT', expected 'NO_FAULT'" in lines[1]
    assert lines[2].startswith("---- banner-ez-array@3 -> 13: not attempted")
    assert lines[3] == "1 changed, 1 failed, 1 not run (3 rows)"
    assert "rtupoll: row 2: huiwen-aq@2 -> 12: not the device" in first.stderr
    assert bus.addresses() == {"radar-level@1": 11, "huiwen-aq@2": 2, "banner-ez-array@3": 3}

    bus.set(2, "co2_failure", "NO_FAULT")  # the technician fixed the sensor
    second = run("set-address", "-p", bus.port, *FAST, "-b", "9600", "--yes", "--plan",
                 str(PLAN))
    assert second.returncode == 0, second.stderr
    assert [line[:5] for line in second.stdout.splitlines()[:3]] == ["skip ", "ok   ", "ok   "]
    assert second.stdout.splitlines()[3] == "2 changed, 1 already done (3 rows)"
    assert bus.addresses() == {"radar-level@1": 11, "huiwen-aq@2": 12, "banner-ez-array@3": 13}

    third = run("set-address", "-p", bus.port, *FAST, "-b", "9600", "--yes", "--format", "json",
                "--plan", str(PLAN))
    assert third.returncode == 0
    assert [json.loads(line)["status"] for line in third.stdout.splitlines()] == \
        ["already done"] * 3


def test_json_report_says_what_was_and_was_not_changed(sim: Sim) -> None:
    bus = three(sim)
    result = run("set-address", "-p", bus.port, *FAST, "-b", "9600", "--yes", "--format", "json",
                 "--plan", str(PLAN))
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(r["row"], r["status"], r["exit_code"]) for r in rows] == [
        (1, "changed", 0), (2, "failed", 8), (3, "not run", None)]
    assert result.returncode == 8


def test_profiles_with_different_baud_rates_need_one_for_the_bus(sim: Sim) -> None:
    bus = three(sim)
    result = run("set-address", "-p", bus.port, *FAST, "--yes", "--plan", str(PLAN))
    assert result.returncode == 2 and "give --baudrate" in result.stderr
    assert "banner-ez-array 19200" in result.stderr


# -- the interactive field workflow, through a real pty --------------------------------


class Terminal:
    """The master side of a pty a command runs on: type, and wait for text."""

    def __init__(self, argv: list[str]) -> None:
        self.fd, slave = os.openpty()
        self.proc = rtupoll_popen(argv, stdin=slave, stdout=slave, stderr=slave,
                                     close_fds=True)
        os.close(slave)
        self.screen = ""

    def expect(self, text: str, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while text not in self.screen:
            left = deadline - time.monotonic()
            assert left > 0, f"{text!r} did not appear; the screen shows:\n{self.screen}"
            ready, _, _ = select.select([self.fd], [], [], left)
            if ready:
                try:
                    self.screen += os.read(self.fd, 4096).decode(errors="replace")
                except OSError:  # the command exited and closed its side
                    assert text in self.screen, self.screen
        seen, self.screen = self.screen.split(text, 1)
        return seen + text

    def type(self, text: str) -> None:
        os.write(self.fd, text.encode())

    def close(self) -> int:
        code = self.proc.wait(timeout=60)
        os.close(self.fd)
        return code

    def __enter__(self) -> Terminal:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:  # a failed expectation: do not leave it running
            self.proc.kill()
            self.proc.wait(timeout=10)


def connect_new_sensor(bus: SimulatedBus, device: str) -> None:
    """Wire one more factory-fresh sensor onto the simulated bus."""
    bus.connect(device)


def test_interactive_gives_each_new_sensor_the_next_free_address(sim: Sim) -> None:
    bus = sim("radar-level@1", "huiwen-aq@10", tick=None)  # 10 is taken already
    with Terminal([sys.executable, "-m", "rtupoll", "set-address", "-p", bus.port, *FAST,
                      "--interactive", "radar-level@1", "10"]) as term:
        term.expect("gets the next free address from 10.")
        term.expect("press Enter")
        term.type("\n")
        step = term.expect("So far: 1 sensor readdressed (11).")
        assert "10 is taken" in step and "ok   radar-level@1 -> 11: changed" in step
        assert "Label this sensor \x1b[1m11\x1b[0m." in step  # bold, on a real terminal

        connect_new_sensor(bus, "radar-level@1")
        term.expect("press Enter")
        term.type("\n")
        step = term.expect("So far: 2 sensors readdressed (11, 12).")
        assert "ok   radar-level@1 -> 12" in step

        term.expect("press Enter")
        term.type("\n")  # nothing connected this time
        term.expect("No sensor answers at 1: check its wiring and power")
        term.expect("press Enter")
        term.type("q\n")
        assert term.close() == 0
    assert sorted(d.address for d in bus.device_list()) == [10, 11, 12]


def test_interrupting_the_interactive_session_prints_the_summary(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    with Terminal([sys.executable, "-m", "rtupoll", "set-address", "-p", bus.port, *FAST,
                      "--interactive", "radar-level@1"]) as term:
        term.expect("gets the next free address from 2.")
        term.expect("press Enter")
        term.type("\n")
        term.expect("So far: 1 sensor readdressed (2).")
        term.expect("press Enter")
        term.proc.send_signal(signal.SIGINT)  # Ctrl-C
        term.expect("So far: 1 sensor readdressed (2).")
        term.expect("rtupoll: interrupted")
        assert term.close() == 130


FACTORY = PLAN.with_name("factory.csv")  # three sensors, all at address 1 from the factory


def test_a_plan_of_factory_fresh_sensors_is_run_again_for_each_one(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)  # the first sensor is connected
    first = run("set-address", "-p", bus.port, *FAST, "--yes", "--plan", str(FACTORY))
    assert first.returncode == 4, first.stderr
    lines = first.stdout.splitlines()
    assert lines[0].startswith("ok   radar-level@1 -> 10: changed")
    assert lines[1].startswith("FAIL radar-level@1 -> 11: no sensor answers at 1: connect "
                               "the next one (alone at 1) and run the plan again")
    assert lines[2].startswith("---- radar-level@1 -> 12: not attempted")

    connect_new_sensor(bus, "radar-level@1")  # the first stays on the bus, at 10
    second = run("set-address", "-p", bus.port, *FAST, "--yes", "--plan", str(FACTORY))
    assert second.returncode == 4, second.stderr
    assert [line[:4] for line in second.stdout.splitlines()[:3]] == ["skip", "ok  ", "FAIL"]
    assert "already done: answers at 10" in second.stdout.splitlines()[0]

    connect_new_sensor(bus, "radar-level@1")
    third = run("set-address", "-p", bus.port, *FAST, "--yes", "--plan", str(FACTORY))
    assert third.returncode == 0, third.stderr
    assert third.stdout.splitlines()[3] == "1 changed, 2 already done (3 rows)"
    assert sorted(d.address for d in bus.device_list()) == [10, 11, 12]


def test_on_a_terminal_the_plan_asks_for_each_factory_fresh_sensor(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    with Terminal([sys.executable, "-m", "rtupoll", "set-address", "-p", bus.port, *FAST,
                   "--plan", str(FACTORY)]) as term:
        term.expect("Change 3 address(es)")
        term.type("y\n")
        term.expect("ok   radar-level@1 -> 10: changed")
        term.expect("Connect the sensor for row 2 (radar-level, to become 11) alone at "
                    "address 1, then press Enter (q to stop): ")
        connect_new_sensor(bus, "radar-level@1")
        term.type("\n")
        term.expect("ok   radar-level@1 -> 11: changed")
        term.expect("Connect the sensor for row 3")
        term.type("\n")  # nothing connected this time
        term.expect("No sensor answers at 1: check its wiring and power.")
        term.expect("Connect the sensor for row 3")
        term.type("q\n")
        term.expect("---- radar-level@1 -> 12: not attempted (stopped)")
        term.expect("2 changed, 1 not run (3 rows)")
        assert term.close() == 0
    assert sorted(d.address for d in bus.device_list()) == [10, 11]


def test_a_dry_run_of_factory_fresh_sensors_says_to_connect_them_one_at_a_time() -> None:
    result = run("set-address", "-p", "/dev/null", "--dry-run", "--plan", str(FACTORY))
    assert result.returncode == 0, result.stderr
    assert ("Rows 1, 2, 3 each expect a device at 1: connect them one at a time."
            in result.stdout)
