"""Why a port will not open, worded for the platform in use (``rtupoll.io.port_errors``)
and the latency advice (``rtupoll.io.latency``): pure functions of the platform and the
error, so each platform's every case is checked here. The errors are the ones each
platform's pyserial raises: POSIX ``OSError``s with an errno, Windows's
``SerialException("could not open port 'COM3': PermissionError(13, ...)")`` with none.
The installed command's wording is checked at the end, as a user meets it."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest
import serial
from cli_runner import rtupoll

from rtupoll.io.latency import latency_timer, latency_warning
from rtupoll.io.port_errors import example_port, open_error, present_ports

WIN_BUSY = serial.SerialException(
    "could not open port 'COM3': PermissionError(13, 'Access is denied.', None, 5)")
WIN_MISSING = serial.SerialException(
    "could not open port 'COM7': FileNotFoundError(2, 'The system cannot find the file "
    "specified.', None, 2)")
ADAPTERS = [("COM3", "USB Serial Port (COM3)"), ("COM4", "Silicon Labs CP210x (COM4)")]
LINUX_ADAPTERS = [("/dev/ttyUSB0", "FT232R USB UART - FT232R USB UART")]


def missing(path: str) -> OSError:
    return FileNotFoundError(errno.ENOENT, f"could not open port {path}: No such file")


def test_windows_busy_names_the_one_program_rule() -> None:
    said = open_error("COM3", WIN_BUSY, platform="win32", present=ADAPTERS)
    assert said.startswith("COM3 is in use by another program: Windows lets one program at "
                           "a time have a serial port")
    assert "\n" not in said and "fuser" not in said


def test_windows_missing_lists_the_com_ports_with_their_descriptions() -> None:
    said = open_error("COM7", WIN_MISSING, platform="win32", present=ADAPTERS)
    assert said == ("COM7 does not exist (serial ports present: COM3 (USB Serial Port "
                    "(COM3)), COM4 (Silicon Labs CP210x (COM4)))")
    assert open_error("COM7", WIN_MISSING, platform="win32", present=[]) == \
        "COM7 does not exist (no serial adapter is present: is it plugged in?)"


def test_a_linux_name_on_windows_says_the_windows_form() -> None:
    said = open_error("/dev/ttyUSB0", WIN_MISSING, platform="win32", present=ADAPTERS)
    assert "that is a Linux name: on Windows a serial port is COM3, COM4" in said
    assert "Ports (COM & LPT)" in said and "COM3 (USB Serial Port (COM3))" in said


@pytest.mark.parametrize(("platform", "form"), [
    ("linux", "/dev/ttyUSB0, /dev/ttyACM0"), ("darwin", "/dev/cu.usbserial-...")])
@pytest.mark.parametrize("name", ["COM3", "com12", "\\\\.\\COM10"])
def test_a_windows_name_elsewhere_says_the_local_form(platform: str, form: str, name: str
                                                      ) -> None:
    said = open_error(name, missing(name), platform=platform, present=LINUX_ADAPTERS)
    assert said == (f"{name} does not exist (that is a Windows name: here a serial port "
                    f"is {form}; serial ports present: /dev/ttyUSB0 (FT232R USB UART - "
                    "FT232R USB UART))")


@pytest.mark.parametrize("platform", ["linux", "win32", "darwin"])
@pytest.mark.parametrize("name", ["127.0.0.1:502", "localhost:5020", "[::1]:502",
                                  "gw.example:4001"])
def test_a_gateway_address_without_tcp_says_to_write_tcp(platform: str, name: str) -> None:
    exc = WIN_MISSING if platform == "win32" else missing(name)
    said = open_error(name, exc, platform=platform, present=ADAPTERS)
    assert said == (f"{name} does not exist (a gateway is written tcp://{name}; a serial "
                    f"server rfc2217://{name})")
    assert "plugged in" not in said


def test_a_missing_linux_port_lists_what_is_present() -> None:
    said = open_error("/dev/ttyUSB1", missing("/dev/ttyUSB1"), platform="linux",
                      present=LINUX_ADAPTERS)
    assert said == ("/dev/ttyUSB1 does not exist (serial ports present: /dev/ttyUSB0 "
                    "(FT232R USB UART - FT232R USB UART))")
    assert open_error("/dev/ttyUSB1", missing("x"), platform="linux", present=[]) == \
        "/dev/ttyUSB1 does not exist (no serial adapter is present: is it plugged in?)"


@pytest.mark.parametrize(("platform", "tool"), [("linux", "fuser"), ("darwin", "lsof")])
def test_posix_busy_says_which_tool_shows_the_holder(platform: str, tool: str) -> None:
    said = open_error("/dev/ttyUSB0", OSError(errno.EAGAIN, "Could not exclusively lock"),
                      platform=platform)
    assert said == ("/dev/ttyUSB0 is busy: another program has it open (close it, or stop "
                    f"the service using it: '{tool} /dev/ttyUSB0' shows which)")


def test_permission_names_the_devices_group_to_join() -> None:
    said = open_error("/dev/ttyUSB0", PermissionError(errno.EACCES, "x"), platform="linux",
                      group_of=lambda path: "dialout")
    assert said == ("permission denied opening /dev/ttyUSB0; add yourself to the 'dialout' "
                    "group and log in again")


@pytest.mark.parametrize("group", ["root", ""])
def test_permission_on_a_device_of_root_never_says_join_root(group: str) -> None:
    said = open_error("/dev/ttyUSB0", PermissionError(errno.EACCES, "x"), platform="linux",
                      group_of=lambda path: group)
    assert "'root' group" not in said and "join" not in said
    assert "udev rule" in said and "dialout (uucp on Arch)" in said


def test_the_other_cases_keep_their_words() -> None:
    assert open_error("/tmp/x", OSError(errno.ENOTTY, "x"), platform="linux") == \
        "/tmp/x is not a serial port"
    assert open_error("/dev/ttyS0", ValueError("bad baud"), platform="linux") == \
        "/dev/ttyS0: bad baud"
    assert open_error("COM3", serial.SerialException("odd"), platform="win32") == \
        "cannot open COM3: odd"


def test_examples_of_a_port_are_in_the_platforms_form() -> None:
    assert [example_port(p) for p in ("linux", "win32", "darwin")] == [
        "/dev/ttyUSB0", "COM3", "/dev/cu.usbserial-0001"]


class Registry:
    """HKLM as the FTDI driver leaves it: one adapter at COM3."""

    def __init__(self, keys: dict[str, dict[str, object]]) -> None:
        self.keys = keys

    def subkeys(self, key: str) -> list[str]:
        prefix = key + "\\"
        return sorted({k[len(prefix):].split("\\")[0] for k in self.keys if
                       k.startswith(prefix)})

    def value(self, key: str, name: str) -> object:
        return self.keys.get(key, {}).get(name)


FTDI = r"SYSTEM\CurrentControlSet\Enum\FTDIBUS"
REGISTRY = Registry({
    FTDI + r"\VID_0403+PID_6001+A10KXYZA\0000\Device Parameters": {
        "PortName": "COM3", "LatencyTimer": 16},
    FTDI + r"\VID_0403+PID_6015+DN05ABCD\0000\Device Parameters": {
        "PortName": "COM11", "LatencyTimer": 1}})


def test_windows_latency_timer_from_the_ftdi_drivers_registry() -> None:
    assert latency_timer("COM3", platform="win32", registry=REGISTRY) == pytest.approx(0.016)
    assert latency_timer("com3", platform="win32", registry=REGISTRY) == pytest.approx(0.016)
    assert latency_timer("\\\\.\\COM11", platform="win32", registry=REGISTRY) == \
        pytest.approx(0.001)
    assert latency_timer("COM5", platform="win32", registry=REGISTRY) is None  # not FTDI
    assert latency_timer("COM3", platform="win32", registry=Registry({})) is None
    assert latency_timer("rfc2217://h:1", platform="win32", registry=REGISTRY) is None


def test_the_latency_advice_is_the_platforms() -> None:
    win = latency_warning("COM3", 0.016, platform="win32")
    assert win == ("COM3: the USB adapter's latency timer is 16 ms, added to every reply; "
                   "set it to 1 in Device Manager: the port's Properties, Port Settings, "
                   "Advanced, Latency Timer (msec) (16 by default), then reopen it")
    linux = latency_warning("/dev/ttyUSB0", 0.016, platform="linux")
    assert linux is not None and "sudo tee /sys/bus/usb-serial/devices/ttyUSB0" in linux
    assert latency_warning("COM3", 0.001, platform="win32") is None


def test_the_installed_command_says_it_in_one_line(tmp_path: Path) -> None:
    """As a user meets it on Linux: a gateway's address without tcp://, a Windows name."""
    for port, words in [("127.0.0.1:502", "a gateway is written tcp://127.0.0.1:502"),
                        ("COM3", "that is a Windows name: here a serial port is")]:
        ran = rtupoll("read", "-p", port, "huiwen-aq@3", "co2")
        assert ran.returncode == 3, ran.stderr
        assert ran.stderr.count("\n") == 1 and words in ran.stderr, ran.stderr
        ran = rtupoll("poll", "--once", "-p", port, "huiwen-aq@3")
        assert ran.returncode == 3 and words in ran.stderr, ran.stderr
    assert not os.path.exists("COM3")


def test_a_port_listing_that_fails_lists_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    """pyserial's Windows listing under Wine 8.0 fails on import (its cfgmgr32 has no
    CM_MapCrToWin32Err): the advice goes without the list, never a traceback."""
    from serial.tools import list_ports

    def broken() -> list[object]:
        raise AttributeError("function 'CM_MapCrToWin32Err' not found")

    monkeypatch.setattr(list_ports, "comports", broken)
    assert present_ports() == []
