"""A USB-serial adapter's latency timer: what it is set to, and how to lower it.

An FTDI adapter holds received bytes up to its latency timer before passing them on
(16 ms by default), so every reply seems that much slower; 1 ms is what a Modbus line
wants. Linux shows it in sysfs (``/sys/bus/usb-serial/devices/ttyUSBn/latency_timer``,
in ms; a udev rule sets it for good); Windows's FTDI driver keeps it in the registry
(``HKLM\\SYSTEM\\CurrentControlSet\\Enum\\FTDIBUS\\<device>\\0000\\Device Parameters``,
``PortName`` = ``COM3``, ``LatencyTimer`` in ms), set in Device Manager: the port's
Properties, Port Settings, Advanced, Latency Timer. The platform and the registry are
arguments, so both forms are tested on Linux.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from typing import Protocol

LATENCY_OK = 0.001  # seconds: an adapter latency timer above this is worth lowering
UDEV_RULE = ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", '
             'ATTR{latency_timer}="1"')
FTDIBUS = r"SYSTEM\CurrentControlSet\Enum\FTDIBUS"


class Registry(Protocol):
    """The part of HKEY_LOCAL_MACHINE read here (``winreg``'s, or a test's)."""

    def subkeys(self, key: str) -> list[str]: ...

    def value(self, key: str, name: str) -> object: ...


def latency_timer(port: str, *, root: str = "/", platform: str | None = None,
                  registry: Registry | None = None) -> float | None:
    """``port``'s adapter latency timer in seconds, or None for any other port or when
    unknown. ``root``: where ``/sys`` and ``/dev`` are looked up (tests give a tree of
    their own); ``registry``: Windows's (tests give one of their own)."""
    from rtupoll.io.port_names import device_path

    if "://" in port.replace("nodtr://", ""):
        return None
    path = device_path(port)
    if (platform or sys.platform) == "win32":
        return _from_registry(path, registry or _WinReg())
    if root != "/":
        path = os.path.join(root, path.lstrip("/"))
    tty = os.path.basename(os.path.realpath(path))
    if not tty.startswith("ttyUSB"):
        return None
    try:
        with open(os.path.join(root, "sys/bus/usb-serial/devices", tty, "latency_timer")) as f:
            return int(f.read().strip()) / 1000
    except (OSError, ValueError):
        return None


def _from_registry(port: str, registry: Registry) -> float | None:
    name = port.upper().removeprefix("\\\\.\\")
    try:
        for device in registry.subkeys(FTDIBUS):
            params = f"{FTDIBUS}\\{device}\\0000\\Device Parameters"
            if str(registry.value(params, "PortName") or "").upper() == name:
                ms = registry.value(params, "LatencyTimer")
                return int(ms) / 1000 if isinstance(ms, int) else None
    except OSError:  # no FTDI driver, no access
        return None
    return None


def latency_warning(port: str, latency: float | None, *, platform: str | None = None
                    ) -> str | None:
    """One line for the user when ``port``'s adapter latency timer is above 1 ms."""
    from rtupoll.io.port_names import device_path

    if latency is None or latency <= LATENCY_OK:
        return None
    said = f"{port}: the USB adapter's latency timer is {latency * 1000:g} ms, added to every reply"
    if (platform or sys.platform) == "win32":
        return (f"{said}; set it to 1 in Device Manager: the port's Properties, Port "
                "Settings, Advanced, Latency Timer (msec) (16 by default), then reopen it")
    tty = os.path.basename(os.path.realpath(device_path(port)))
    return (f"{said}; lower it with 'echo 1 | sudo tee /sys/bus/usb-serial/devices/"
            f"{tty}/latency_timer' or for good with the udev rule {UDEV_RULE}")


class _WinReg:
    """HKEY_LOCAL_MACHINE through ``winreg`` (Windows only; elsewhere: no keys)."""

    def __init__(self) -> None:
        try:
            import winreg
        except ImportError:
            self._reg: object = None
        else:
            self._reg = winreg

    def _open(self, key: str) -> object:
        reg: object = self._reg
        if reg is None:
            raise OSError("no registry")
        opener: Callable[..., object] = reg.OpenKey  # type: ignore[attr-defined]
        return opener(reg.HKEY_LOCAL_MACHINE, key)  # type: ignore[attr-defined]

    def subkeys(self, key: str) -> list[str]:
        names: list[str] = []
        with self._open(key) as handle:  # type: ignore[attr-defined]
            while True:
                try:
                    names.append(self._reg.EnumKey(handle, len(names)))  # type: ignore[attr-defined]
                except OSError:
                    return names

    def value(self, key: str, name: str) -> object:
        try:
            with self._open(key) as handle:  # type: ignore[attr-defined]
                return self._reg.QueryValueEx(handle, name)[0]  # type: ignore[attr-defined]
        except OSError:
            return None
