"""The commands that run until stopped, on Windows (CPython 3.13 under Wine), and the one
that needs a console (``set-address --interactive``): ``poll``
(until Ctrl-C, -o, the live table, --http, --metrics, --serve, MQTT), ``sniff`` with
``--capture`` on a COM port that is the simulator's tap, ``simulate --tcp`` read from
Linux, and the demo (``poll --simulate``). A Ctrl-C is a SIGINT to the Windows process's
Unix one, which Wine turns into its CTRL_C_EVENT (tests/windows/wine.py, ``Running``).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from brokers import Broker, free_port, listening
from cli_runner import rtupoll as linux_rtupoll
from conftest import ANSWERED, PATIENT
from wine import Console, Wine, setup, winpath

from rtupoll.sim.runner import SimulatedBus

pytestmark = pytest.mark.windows
Sim = Callable[..., SimulatedBus]
MBPOLL = shutil.which("mbpoll") or "mbpoll"


@pytest.fixture(scope="module")
def wine(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Wine, dict[str, Path]]]:
    setup()
    here = tmp_path_factory.mktemp("com")
    links = {name: here / name.lower() for name in ("COM5", "COM6")}  # COM6: a tap
    with Wine(ports=links) as running:
        yield running, links


def records(lines: list[str]) -> list[dict[str, Any]]:
    return [json.loads(line) for line in lines if line.startswith("{")]


def until(ready: Callable[[], bool], what: str, timeout: float = 60) -> None:
    """A hang guard: wait until ``ready()``."""
    deadline = time.monotonic() + timeout
    while not ready():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.05)


def get(url: str) -> str:
    with urllib.request.urlopen(url, timeout=ANSWERED) as reply:
        return str(reply.read().decode())


def test_poll_runs_until_ctrl_c_and_ends_0_with_its_file_written(
        wine: tuple[Wine, dict[str, Path]], sim: Sim, tmp_path: Path) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 777)
    out = tmp_path / "readings.jsonl"
    out.write_text('{"time":"2026-')  # what a power cut left: cut off before appending
    with w.running("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--interval", "0.2",
                   "--format", "json", "-o", winpath(out), "huiwen-aq@3", "-f", "co2") as poll:
        until(lambda: out.exists() and out.read_text().count("\n") >= 3, "3 records in -o")
        code, err = poll.interrupt()
    assert code == 0, err
    assert b"\r" not in out.read_bytes()  # a record's line ends "\n", as on Linux
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(recs) >= 3 and {(r["field"], r["value"], r["status"]) for r in recs} == {
        ("co2", 777, "ok")}
    assert "cut off a partial last line (14 bytes)" in err, err


def test_the_live_table_shows_the_values(wine: tuple[Wine, dict[str, Path]], sim: Sim
                                         ) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 1234)
    with w.running("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--interval", "0.3",
                   "huiwen-aq@3") as poll:
        lines = poll.wait(lambda lines: any("co2" in x and "1234" in x for x in lines))
        code, err = poll.interrupt()
    assert code == 0, err
    assert any("huiwen-aq@3" in line for line in lines), lines


def test_a_one_shot_command_interrupted_is_exit_130(wine: tuple[Wine, dict[str, Path]],
                                                    sim: Sim) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    with w.running("read", "-p", "COM5", "--timeout", "30", "huiwen-aq@9", "co2") as read:
        bus.wait_wire(1, direction="in", timeout=60)  # it is waiting for the reply now
        code, err = read.interrupt()
    assert code == 130, err
    assert err.strip().splitlines()[-1] == "rtupoll: interrupted", err


def test_http_and_metrics_serve_the_polled_values(wine: tuple[Wine, dict[str, Path]],
                                                  sim: Sim) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 901)
    http, metrics = free_port(), free_port()
    with w.running("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--interval", "0.3",
                   "--format", "json", "--http", f"127.0.0.1:{http}", "--metrics",
                   f"127.0.0.1:{metrics}", "huiwen-aq@3", "-f", "co2,temperature") as poll:
        poll.wait(lambda lines: len(records(lines)) >= 2)
        until(lambda: listening(http) and listening(metrics), "both listen")
        state = json.loads(get(f"http://127.0.0.1:{http}/api/state"))
        scraped = get(f"http://127.0.0.1:{metrics}/metrics")
        code, err = poll.interrupt()
    assert code == 0, err
    assert "901" in json.dumps(state), state
    gauges = {line.split()[0].split("{")[0]: float(line.split()[-1]) for line in
              scraped.splitlines() if line.startswith("rtupoll_co2_ppm")}
    assert gauges == {"rtupoll_co2_ppm": 901.0}, scraped


def test_serve_lets_mbpoll_on_linux_read_through_the_windows_gateway(
        wine: tuple[Wine, dict[str, Path]], sim: Sim) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 640)
    port = free_port()
    with w.running("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--interval", "0.5",
                   "--format", "json", "--serve", f"127.0.0.1:{port}", "huiwen-aq@3") as poll:
        until(lambda: listening(port), "the gateway listens")
        read = subprocess.run([MBPOLL, "-m", "tcp", "-p", str(port), "-1", "-o", "10", "-a", "3",
                               "-t", "3", "-r", "30007", "-c", "4", "127.0.0.1"],
                              capture_output=True, text=True, timeout=60)
        code, err = poll.interrupt()
    assert read.returncode == 0, read.stdout + read.stderr
    got = [int(line.split()[-1]) for line in read.stdout.splitlines() if line.startswith("[")]
    assert got == list(bus.registers(3, "input", 0x7536, 4)) and got[3] == 640
    assert code == 0, err


def test_mqtt_publishes_the_values_to_a_real_broker(wine: tuple[Wine, dict[str, Path]],
                                                    sim: Sim, tmp_path: Path) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 1175)
    with Broker(tmp_path) as broker:
        sub = broker.subscribe("win/#")
        with w.running("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--interval", "0.3",
                       "--format", "json", "--mqtt", f"{broker.url}/win", "--mqtt-id", "win",
                       "huiwen-aq@3", "-f", "co2") as poll:
            state = sub.wait(lambda m: m.topic == "win/huiwen-aq_3")
            sub.wait(lambda m: m.topic == "win/bridge/state" and m.payload == "online")
            assert broker.retained("win/bridge/state") == "online"
            code, err = poll.interrupt()
        assert code == 0, err
        assert json.loads(state.payload)["co2"] == 1175, state
        until(lambda: broker.retained("win/bridge/state") == "offline", "offline on a stop")


def test_sniff_and_capture_on_a_com_port_that_hears_the_line(
        wine: tuple[Wine, dict[str, Path]], sim: Sim, tmp_path: Path) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", link=str(links["COM5"]), tap=str(links["COM6"]), tick=None)
    bus.set(3, "co2", 650)
    capture = tmp_path / "line1.pcapng"
    with w.running("sniff", "-p", "COM6", "-b", "9600", "--format", "json", "--capture",
                   winpath(capture), "huiwen-aq@3") as sniff:
        # the Linux master on the same line, until the sniffer (which does not say when it
        # has the port open) has heard a transaction whole
        deadline = time.monotonic() + 60
        while not records(sniff.lines):
            assert time.monotonic() < deadline, "the sniffer heard nothing in 60 s"
            read = linux_rtupoll("read", "-p", bus.port, *PATIENT, "huiwen-aq@3", "co2")
            assert read.returncode == 0, read.stderr
            time.sleep(0.2)
        lines = sniff.wait(lambda lines: len(records(lines)) >= 1)
        code, err = sniff.interrupt()
    assert code == 0, err
    recs = records(lines)
    assert {(r["device"], r["field"], r["value"], r["status"]) for r in recs} == {
        ("huiwen-aq@3", "co2", 650, "ok")}, recs
    offline = linux_rtupoll("sniff", "--read", str(capture), "--format", "json", "huiwen-aq@3")
    assert offline.returncode == 0, offline.stderr
    again = records(offline.stdout.splitlines())
    assert len(again) >= len(recs) and {r["value"] for r in again} == {650}


def test_simulate_tcp_serves_a_linux_master(wine: tuple[Wine, dict[str, Path]]) -> None:
    w, _ = wine
    port = free_port()
    with w.running("simulate", "--tcp", f"127.0.0.1:{port}", "huiwen-aq@3",
                   "--set", "huiwen-aq@3.co2=555") as simulate:
        until(lambda: listening(port), "simulate listens")
        read = linux_rtupoll("read", "-p", f"tcp://127.0.0.1:{port}", *PATIENT, "--format",
                             "json", "huiwen-aq@3", "co2")
        code, err = simulate.interrupt()
    assert read.returncode == 0, read.stderr
    assert [r["value"] for r in records(read.stdout.splitlines())] == [555]
    assert code == 0, err


def test_the_demo_runs_on_windows(wine: tuple[Wine, dict[str, Path]]) -> None:
    w, _ = wine
    ran = w.rtupoll("poll", "--simulate", "--once", "--format", "json")
    assert ran.returncode == 0, ran
    recs = [json.loads(line) for line in ran.stdout.splitlines() if line.startswith("{")]
    assert len({r["device"] for r in recs}) == 5 and {r["status"] for r in recs} == {"ok"}
    with w.running("poll", "--simulate") as demo:  # the live demo, as README says
        demo.wait(lambda lines: any("co2" in line for line in lines))
        code, err = demo.interrupt()
    assert code == 0, err
    # a simulated line on a pty, which Windows has not: one line, exit 2
    ran = w.rtupoll("simulate", "huiwen-aq@3")
    assert ran.returncode == 2 and "--tcp" in ran.stderr, ran
    assert len(ran.stderr.strip().splitlines()) == 1, ran




def test_set_address_interactive_on_a_console(wine: tuple[Wine, dict[str, Path]],
                                              sim: Sim) -> None:
    w, links = wine
    bus = sim("radar-level@1", link=str(links["COM5"]), tick=None)
    with Console(w, "-m", "rtupoll", "set-address", "-p", "COM5", "--interactive",
                 "radar-level@1", "10") as term:
        term.expect("gets the next free address from 10.")
        term.expect("press Enter (q to finish):")
        term.type("\r")
        step = term.expect("So far: 1 sensor readdressed (10).")
        assert "ok   radar-level@1 -> 10: changed" in step, step
        assert bus.addresses() == {"radar-level@1": 10}
        term.expect("press Enter (q to finish):")
        term.type("q\r")
        assert term.close() == 0


def test_the_live_table_on_a_console(wine: tuple[Wine, dict[str, Path]], sim: Sim) -> None:
    w, links = wine
    bus = sim("huiwen-aq@3", "radar-level@2", link=str(links["COM5"]), tick=None)
    bus.set(3, "co2", 1175)
    bus.set(2, "air_gap_cm", 321)
    with Console(w, "-m", "rtupoll", "poll", "-p", "COM5", "-b", "9600", *PATIENT,
                 "--interval", "0.3", "huiwen-aq@3", "radar-level@2") as term:
        shown = term.expect("air_gap_cm")
        shown += term.expect("321")
        term.interrupt()
        assert term.close() == 0
    assert "huiwen-aq@3" in shown and "1175" in shown, shown
