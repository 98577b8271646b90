"""What rtupoll reads of a Windows port besides its bytes, on the Windows CPython under
Wine (tests/windows/wine.py): an FTDI adapter's latency timer from the registry entry its
driver keeps (``HKLM\\SYSTEM\\CurrentControlSet\\Enum\\FTDIBUS\\...\\Device Parameters``,
written here as the driver writes it, and removed after), advised as Device Manager sets
it; a Linux port name typed on Windows; the line's clock, chosen by the resolution of the
Windows build's own ``time.monotonic``. (Wine gives a second program a COM port another
holds, where Windows refuses it: the "in use" wording is checked on Linux only,
tests/io/test_port_errors.py.)"""

from __future__ import annotations

import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from wine import WINE, Wine, environment, setup

from rtupoll.sim.runner import SimulatedBus

pytestmark = pytest.mark.windows
Sim = Callable[..., SimulatedBus]
FTDI = (r"HKLM\SYSTEM\CurrentControlSet\Enum\FTDIBUS\VID_0403+PID_6001+A10RTUPL"
        r"\0000\Device Parameters")


@pytest.fixture(scope="module")
def wine(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Wine, Path]]:
    setup()
    link = tmp_path_factory.mktemp("com") / "com5"
    with Wine(ports={"COM5": link}) as running:
        yield running, link


def reg(*args: str) -> None:
    subprocess.run([WINE, "reg", *args, "/f"], check=True, capture_output=True, timeout=120,
                   env=environment())


def test_an_ftdi_adapters_latency_timer_is_advised_as_device_manager_sets_it(
        wine: tuple[Wine, Path], sim: Sim) -> None:
    running, link = wine
    sim("huiwen-aq@3", link=str(link), tick=None)
    reg("add", FTDI, "/v", "PortName", "/t", "REG_SZ", "/d", "COM5")
    reg("add", FTDI, "/v", "LatencyTimer", "/t", "REG_DWORD", "/d", "16")
    try:
        ran = running.rtupoll("poll", "--once", "-p", "COM5", "-b", "9600", "--format", "json",
                              "huiwen-aq@3")
    finally:
        reg("delete", FTDI.rpartition("\\0000")[0])
    assert ran.returncode == 0, ran
    assert ("rtupoll: COM5: the USB adapter's latency timer is 16 ms, added to every reply; "
            "set it to 1 in Device Manager: the port's Properties, Port Settings, Advanced, "
            "Latency Timer (msec) (16 by default), then reopen it") in ran.stderr, ran
    again = running.rtupoll("poll", "--once", "-p", "COM5", "-b", "9600", "--format", "json",
                            "huiwen-aq@3")
    assert again.returncode == 0 and "latency" not in again.stderr, again  # no FTDI entry


def test_a_linux_port_name_gets_the_windows_form(wine: tuple[Wine, Path]) -> None:
    running, _ = wine
    ran = running.rtupoll("read", "-p", "/dev/ttyUSB0", "huiwen-aq@3", "co2")
    assert ran.returncode == 3, ran
    assert ran.stderr.startswith("rtupoll: /dev/ttyUSB0 does not exist (that is a Linux name: "
                                 "on Windows a serial port is COM3, COM4, ..."), ran
    assert ran.stderr.count("\n") == 1, ran


def test_the_line_clock_is_chosen_by_the_windows_builds_own_monotonic(
        wine: tuple[Wine, Path]) -> None:
    """CPython 3.13's ``time.monotonic`` on Windows is QueryPerformanceCounter (100 ns):
    the line takes it; a 15.6 ms one (3.11, 3.12: GetTickCount64) would give
    ``time.perf_counter``, which is QueryPerformanceCounter on every Windows Python."""
    running, _ = wine
    ran = running.run("-c", "import time; from rtupoll.io import clock; "
                      "m = time.get_clock_info('monotonic'); "
                      "p = time.get_clock_info('perf_counter'); "
                      "print(m.implementation, m.resolution, p.implementation, "
                      "clock.now is time.monotonic, clock.choose(0.015625) is time.perf_counter)")
    assert ran.returncode == 0, ran
    words = ran.stdout.split()
    assert words[0] == "QueryPerformanceCounter()" and float(words[1]) <= 1e-5, ran
    assert words[2] == "QueryPerformanceCounter()", ran
    assert words[3:] == ["True", "True"], ran
