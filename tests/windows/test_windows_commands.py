"""Every one-shot command on Windows: the official CPython 3.13 (win_amd64) under Wine,
rtupoll installed from its wheel, pyserial's Windows backend on COM ports that Wine maps
to the simulator's ptys (COM5, and COM12 for the names from COM10 on, which Windows
opens as ``\\\\.\\COM12``), values checked against the simulator's.

The group runs by itself (``-m windows``; scripts/test runs it after the other runs):
one Wine server for the module, and COM ports that are fixed paths of the module's.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from cli_runner import rtupoll as linux_rtupoll
from conftest import ANSWERED, PATIENT
from wine import Wine, setup, winpath

from rtupoll.config.library import load_library
from rtupoll.sim.runner import SimulatedBus

pytestmark = pytest.mark.windows
Sim = Callable[..., SimulatedBus]


class Windows:
    """The module's Wine server, and the Unix paths its COM ports open."""

    def __init__(self, wine: Wine, links: dict[str, Path]) -> None:
        self.wine, self.links = wine, links

    def rtupoll(self, *args: str, **kwargs: Any) -> Any:
        return self.wine.rtupoll(*args, **kwargs)


@pytest.fixture(scope="module")
def windows(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Windows]:
    setup()
    here = tmp_path_factory.mktemp("com")
    links = {name: here / name.lower() for name in ("COM5", "COM12")}
    with Wine(ports=links) as wine:
        yield Windows(wine, links)


def records(out: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def test_read_prints_the_table_of_the_devices_values(windows: Windows, sim: Sim) -> None:
    bus = sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    bus.set(3, "co2", 1175)
    bus.set(3, "temperature", 23)
    ran = windows.rtupoll("read", "-p", "COM5", *PATIENT, "huiwen-aq@3")
    assert ran.returncode == 0, ran
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip()
            for line in ran.stdout.splitlines() if line.count("|") >= 4}
    assert rows["co2"] == "1175" and rows["temperature"] == "23", ran.stdout
    assert "µg/m³" in ran.stdout  # (the ANSI code page has it: Windows's pipe encoding)


def test_read_json_on_com12_gives_the_simulators_values(windows: Windows, sim: Sim) -> None:
    bus = sim("huiwen-aq@3", "net-irnet-pro@1", link=str(windows.links["COM12"]), tick=None,
              baudrate=None)
    bus.set(1, "concentration", 12.5)
    ran = windows.rtupoll("read", "-p", "COM12", "-b", "9600", "--format", "json", *PATIENT,
                          "net-irnet-pro@1", "concentration")
    assert ran.returncode == 0, ran
    (rec,) = records(ran.stdout)
    assert rec["field"] == "concentration" and rec["value"] == 12.5
    ran = windows.rtupoll("read", "-p", "COM12", "--format", "json", *PATIENT, "huiwen-aq@3",
                          "co2", "humidity")
    assert ran.returncode == 0, ran
    assert {r["field"]: r["value"] for r in records(ran.stdout)} == {
        "co2": bus.get(3, "co2").value, "humidity": bus.get(3, "humidity").value}


def test_read_raw_registers(windows: Windows, sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", link=str(windows.links["COM5"]), tick=None)
    bus.set(1, "concentration", -20.0)
    ran = windows.rtupoll("read", "-p", "COM5", "-b", "9600", *PATIENT, "--format", "json",
                          "--raw", "--modicon", "1", "30007", "--type", "f32", "--order", "DCBA")
    assert ran.returncode == 0, ran
    (rec,) = records(ran.stdout)
    assert rec["value"] == -20.0, rec


def test_a_device_that_does_not_answer_is_exit_4(windows: Windows, sim: Sim) -> None:
    sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    ran = windows.rtupoll("read", "-p", "COM5", "--timeout", "0.1", "huiwen-aq@9", "co2")
    assert ran.returncode == 4, ran
    assert "Traceback" not in ran.stderr and len(ran.stderr.strip().splitlines()) <= 3, ran


def test_write_reads_back(windows: Windows, sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", link=str(windows.links["COM5"]), tick=None)
    ran = windows.rtupoll("write", "-p", "COM5", "-b", "9600", *PATIENT, "net-irnet-pro@1",
                          "calibration_gas_level=50", "--yes")
    assert ran.returncode == 0, ran
    assert bus.get(1, "calibration_gas_level").value == 50
    back = windows.rtupoll("read", "-p", "COM5", "-b", "9600", "--format", "json", *PATIENT,
                           "net-irnet-pro@1", "calibration_gas_level")
    assert [r["value"] for r in records(back.stdout)] == [50], back


def test_write_refuses_a_read_only_field(windows: Windows, sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", link=str(windows.links["COM5"]), tick=None)
    ran = windows.rtupoll("write", "-p", "COM5", "-b", "9600", *PATIENT, "net-irnet-pro@1",
                          "concentration=5", "--yes")
    assert ran.returncode == 8, ran
    assert not [w for w in bus.wire if w.direction == "in"]  # nothing was sent


def test_set_address_moves_a_device_verified(windows: Windows, sim: Sim) -> None:
    bus = sim("radar-level@2", link=str(windows.links["COM5"]), tick=None)
    # (the profile's timeouts: the checks that an address is silent wait them out)
    ran = windows.rtupoll("set-address", "-p", "COM5", "radar-level@2", "12", "--yes",
                          "--format", "json")
    assert ran.returncode == 0, ran
    (rec,) = records(ran.stdout)
    assert rec["status"] == "changed" and rec["new"] == 12
    assert bus.addresses() == {"radar-level@2": 12}


def test_set_address_runs_a_plan_from_a_windows_path(windows: Windows, sim: Sim,
                                                     tmp_path: Path) -> None:
    bus = sim("radar-level@1", "huiwen-aq@2", link=str(windows.links["COM12"]), tick=None)
    plan = tmp_path / "plan.csv"
    plan.write_text("profile,address,new\nradar-level,1,11\nhuiwen-aq,2,12\n")
    ran = windows.rtupoll("set-address", "-p", "COM12", "--plan", winpath(plan),
                          "--yes", "--format", "json")
    assert ran.returncode == 0, ran
    assert [(r["address"], r["new"], r["status"]) for r in records(ran.stdout)] == [
        (1, 11, "changed"), (2, 12, "changed")]
    assert bus.addresses() == {"radar-level@1": 11, "huiwen-aq@2": 12}
    again = windows.rtupoll("set-address", "-p", "COM12", "--plan", winpath(plan),
                            "--yes", "--format", "json")  # safe to re-run: done already
    assert again.returncode == 0, again
    assert bus.addresses() == {"radar-level@1": 11, "huiwen-aq@2": 12}


def test_set_address_dry_run_sends_nothing(windows: Windows, sim: Sim) -> None:
    bus = sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    ran = windows.rtupoll("set-address", "-p", "COM5", "huiwen-aq@3", "12", "--dry-run")
    assert ran.returncode == 0, ran
    assert "03 06" in ran.stdout.upper().replace("0306", "03 06") or "06" in ran.stdout, ran
    assert bus.addresses() == {"huiwen-aq@3": 3}
    assert not [w for w in bus.wire if w.direction == "in"]


def test_scan_finds_and_identifies_the_devices(windows: Windows, sim: Sim,
                                               tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@2", link=str(windows.links["COM5"]), tick=None)
    found = tmp_path / "found.yaml"
    ran = windows.rtupoll("scan", "-p", "COM5", "--baudrate", "9600", "--addresses", "1-4",
                          "--format", "json", "--write-config", winpath(found))
    assert ran.returncode == 0, ran
    assert [(r["address"], r["status"], r["profile"]) for r in records(ran.stdout)] == [
        (2, "identified", "radar-level"), (3, "identified", "huiwen-aq")]
    # the site file it wrote is one that poll takes, on the same COM port
    assert "port: \"COM5\"" in found.read_text(), found.read_text()
    polled = windows.rtupoll("poll", "-c", winpath(found), "--once", "--format", "json")
    assert polled.returncode == 0, polled
    got = {(r["field"], r["value"]) for r in records(polled.stdout)}
    assert ("co2", bus.get(3, "co2").value) in got, polled.stdout
    assert ("air_gap_cm", bus.get(2, "air_gap_cm").value) in got, polled.stdout


def test_guess_ranks_the_register_as_the_device_holds_it(windows: Windows, sim: Sim) -> None:
    bus = sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    bus.set(3, "co2", 812)
    ran = windows.rtupoll("guess", "-p", "COM5", "--address", "3", *PATIENT, "--format", "json",
                          "input:30009:2")
    assert ran.returncode == 0, ran
    best = records(ran.stdout)[0]
    assert (best["address"], best["type"], best["value"]) == (30009, "u16", 812), best


def test_decode_needs_no_port(windows: Windows) -> None:
    ran = windows.rtupoll("decode", "01 04 00 06 00 02 91 CA 01 04 04 00 00 A0 C1 42 14",
                          "--profile", "net-irnet-pro")
    assert ran.returncode == 0, ran
    assert "concentration (0x0006) = -20.00 ppm" in ran.stdout, ran


def test_profiles_list_show_and_check(windows: Windows, tmp_path: Path) -> None:
    listed = windows.rtupoll("profiles", "list", "--format", "json")
    assert listed.returncode == 0, listed
    ids = {json.loads(line)["id"] for line in listed.stdout.splitlines() if line.strip()}
    assert ids == set(load_library().profiles), listed.stdout
    assert "\u25a1" not in listed.stdout and "?" in listed.stdout  # (the code page lacks it)
    utf8 = windows.rtupoll("profiles", "list", "--format", "json", env={"PYTHONUTF8": "1"},
                           encoding="utf-8")  # as README says: UTF-8, every character
    assert utf8.returncode == 0 and "\u25a1" in utf8.stdout, utf8
    shown = windows.rtupoll("profiles", "show", "huiwen-aq")
    assert shown.returncode == 0 and "co2" in shown.stdout and "30009" in shown.stdout, shown
    mine = tmp_path / "xy-md02.yaml"
    root = Path(__file__).resolve().parents[2]
    text = (root / "profiles" / "xy-md02.yaml").read_text()
    mine.write_text(text)
    checked = windows.rtupoll("profiles", "check", winpath(mine))
    assert checked.returncode == 0, checked
    line = text.splitlines().index("addressing: pdu") + 1
    mine.write_text(text.replace("addressing: pdu", "addressing: sideways"))
    broken = windows.rtupoll("profiles", "check", winpath(mine))
    assert broken.returncode == 2, broken
    assert broken.stderr.startswith(f"{winpath(mine)}:{line}: addressing"), broken
    assert "Traceback" not in broken.stderr


def test_a_missing_com_port_is_exit_3_in_one_line(windows: Windows) -> None:
    ran = windows.rtupoll("read", "-p", "COM9", "huiwen-aq@3", "co2")
    assert ran.returncode == 3, ran
    assert "COM9" in ran.stderr and "Traceback" not in ran.stderr, ran


def test_poll_once_and_a_site_file_on_com_ports(windows: Windows, sim: Sim,
                                                tmp_path: Path) -> None:
    air = sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    tank = sim("radar-level@2", link=str(windows.links["COM12"]), tick=None)
    air.set(3, "co2", 640)
    tank.set(2, "air_gap_cm", 321)
    site = tmp_path / "site.yaml"
    site.write_text(
        "buses:\n"
        f"  - {{name: line1, port: COM5, baudrate: 9600, devices: [{{name: air, profile: huiwen-aq,"
        f" address: 3, timeout: {ANSWERED:g}, fields: [co2, temperature]}}]}}\n"
        f"  - {{name: line2, port: COM12, baudrate: 9600, devices: [{{name: tank, profile:"
        f" radar-level, address: 2, timeout: {ANSWERED:g}}}]}}\n")
    ran = windows.rtupoll("poll", "-c", winpath(site), "--once", "--format", "json")
    assert ran.returncode == 0, ran
    got = {(r["device"], r["field"]): r["value"] for r in records(ran.stdout)}
    assert got[("air", "co2")] == 640
    assert got[("air", "temperature")] == air.get(3, "temperature").value
    assert got[("tank", "air_gap_cm")] == 321
    csv = windows.rtupoll("poll", "-p", "COM5", "-b", "9600", *PATIENT, "--once", "--format",
                          "csv", "huiwen-aq@3")
    assert csv.returncode == 0 and ",co2,640," in csv.stdout, csv


def test_poll_once_with_a_dead_device_is_exit_9(windows: Windows, sim: Sim) -> None:
    sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None, faults=["3:dead"])
    ran = windows.rtupoll("poll", "-p", "COM5", "--timeout", "0.1", "--once", "--format",
                          "json", "huiwen-aq@3")
    assert ran.returncode == 9, ran
    assert "huiwen-aq@3" in ran.stderr


def test_the_linux_peer_reads_the_same_line(windows: Windows, sim: Sim) -> None:
    # (the Linux side of the same pty: what the Windows command read is the line's)
    bus = sim("huiwen-aq@3", link=str(windows.links["COM5"]), tick=None)
    linux = linux_rtupoll("read", "-p", bus.port, "--format", "json", "huiwen-aq@3", "co2")
    win = windows.rtupoll("read", "-p", "COM5", "--format", "json", *PATIENT, "huiwen-aq@3",
                          "co2")
    assert linux.returncode == win.returncode == 0, (linux, win)
    assert records(linux.stdout)[0]["value"] == records(win.stdout)[0]["value"]
