"""Why a port will not open, in one line that says what to do, on the platform in use.

A port that will not open is the commonest field problem, and "could not open port" helps
nobody. ``open_error`` and ``gateway_error`` turn the error into the cause and the fix:
missing (with the serial ports present, and a hint when the name is in another
platform's form, or is a gateway's ``HOST:PORT`` without ``tcp://``), busy (another
program holds it; on Windows only one program at a time may), permission denied (the
group to join, or a udev rule where the device is root's), not a serial port, a
gateway that refuses, cannot be resolved, is unreachable or does not answer.

Pure: the platform (``sys.platform``'s spelling), the ports present and a device's group
are arguments (their defaults ask this machine), so every case is tested on Linux.

Windows's pyserial raises ``SerialException("could not open port 'COM3':
PermissionError(13, 'Access is denied.', None, 5)")``: no ``errno``, so the Windows error
is told by its class in that text (``PermissionError``: Windows's ERROR_ACCESS_DENIED,
another program has the port; ``FileNotFoundError``: ERROR_FILE_NOT_FOUND, no such port).
"""

from __future__ import annotations

import errno
import os
import re
import sys
from collections.abc import Callable, Sequence

# (device, description) of the serial ports present, as pyserial's list_ports has them
Present = Sequence[tuple[str, str]]

_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):(\d{1,5})$")
_WINDOWS_NAME = re.compile(r"^(\\\\\.\\)?COM\d+$", re.IGNORECASE)
# the groups serial devices usually belong to: Debian, Ubuntu, Fedora, Raspberry Pi OS;
# Arch; (root's own: a udev rule gives them one of these)
USUAL_GROUPS = "dialout (uucp on Arch)"


def example_port(platform: str | None = None) -> str:
    """A serial port's name as this platform spells it, for hints."""
    platform = platform or sys.platform
    return {"win32": "COM3", "darwin": "/dev/cu.usbserial-0001"}.get(platform, "/dev/ttyUSB0")


def present_ports() -> list[tuple[str, str]]:
    """The serial ports this machine has, with their USB descriptions (pyserial's
    ``list_ports``), adapters first; ports that are only names (a PC's legacy ttyS with
    nothing behind it: no hardware id) left out."""
    try:
        from serial.tools import list_ports

        ports = list_ports.comports()
    except Exception:  # (advice only: Wine 8.0's cfgmgr32 lacks what pyserial's Windows
        return []      # listing looks up on import, CM_MapCrToWin32Err)
    found = [(p.device, p.description or "") for p in ports if (p.hwid or "n/a") != "n/a"]
    return sorted(found, key=lambda p: (not ("USB" in p[1] or "ACM" in p[0]), p[0]))


def open_error(path: str, exc: BaseException, *, platform: str | None = None,
               present: Present | Callable[[], Present] = present_ports,
               group_of: Callable[[str], str] | None = None) -> str:
    """One line saying why the port ``path`` (a device: ``/dev/ttyUSB0``, ``COM3``; or a
    pyserial URL) did not open, and what to do about it."""
    platform = platform or sys.platform
    code = getattr(exc, "errno", None)
    text = str(exc)
    windows = platform == "win32"
    if windows and "PermissionError(" in text:
        return (f"{path} is in use by another program: Windows lets one program at a time "
                "have a serial port (close the other one: a terminal, Modbus Poll, the "
                "vendor's tool, another rtupoll)")
    if code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY) or "exclusively lock" in text:
        which = f"'lsof {path}'" if platform == "darwin" else f"'fuser {path}'"
        return (f"{path} is busy: another program has it open (close it, or stop the "
                f"service using it: {which} shows which)")
    if code in (errno.EACCES, errno.EPERM):
        return _permission(path, (group_of or _group_of)(path))
    missing = code in (errno.ENOENT, errno.ENXIO, errno.ENODEV) or (
        windows and "FileNotFoundError(" in text) or (
        code is None and not windows and "://" not in path and not os.path.exists(path))
    if missing:
        return f"{path} does not exist{_missing_hint(path, platform, present)}"
    if code in (errno.ENOTTY, errno.EINVAL) or f"({errno.ENOTTY}, " in text:
        # pyserial reports a failed termios call as "Could not configure port: (25, ...)"
        return f"{path} is not a serial port"
    if isinstance(exc, ValueError):
        return f"{path}: {text}"
    return f"cannot open {path}: {text or type(exc).__name__}"


def _permission(path: str, group: str) -> str:
    if group and group != "root":
        return (f"permission denied opening {path}; add yourself to the '{group}' group "
                "and log in again")
    owner = f"it belongs to group '{group}'" if group else "its group is unknown"
    return (f"permission denied opening {path}: {owner}; give the adapter a group with a "
            f"udev rule (GROUP=\"dialout\"), or add yourself to the group serial ports "
            f"usually have, {USUAL_GROUPS}, and log in again")


def _missing_hint(path: str, platform: str, present: Present | Callable[[], Present]) -> str:
    """What to try instead of ``path``, which does not exist (with a leading space)."""
    m = _HOST_PORT.match(path)
    if m and not path.upper().startswith("COM"):
        return f" (a gateway is written tcp://{path}; a serial server rfc2217://{path})"
    ports = list(present() if callable(present) else present)
    listed = ", ".join(f"{d} ({desc})" if desc and desc != d else d for d, desc in ports)
    here = f"; serial ports present: {listed}" if listed else ""
    if platform == "win32" and path.startswith("/dev/"):
        return (f" (that is a Linux name: on Windows a serial port is COM3, COM4, ... as "
                f"Device Manager shows under 'Ports (COM & LPT)'{here})")
    if platform != "win32" and _WINDOWS_NAME.match(path):
        form = "/dev/cu.usbserial-..." if platform == "darwin" else "/dev/ttyUSB0, /dev/ttyACM0"
        return f" (that is a Windows name: here a serial port is {form}{here})"
    if listed:
        return f" (serial ports present: {listed})"
    return " (no serial adapter is present: is it plugged in?)"


def gateway_error(host: str, port: int, exc: BaseException, timeout: float) -> str:
    """One line saying why an RTU-over-TCP gateway did not accept a connection."""
    import socket

    where = f"gateway {host}:{port}"
    if isinstance(exc, ConnectionRefusedError):
        return f"{where} refused the connection (wrong port, or the gateway allows one client)"
    if isinstance(exc, socket.gaierror):
        return f"{where}: cannot resolve {host!r}"
    if isinstance(exc, TimeoutError):  # asyncio's too (3.11+)
        return f"{where} did not answer within {timeout:g} s (unreachable or filtered)"
    code = getattr(exc, "errno", None)
    if code in (errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EHOSTDOWN):
        return f"{where} is unreachable ({os.strerror(code)})"
    return f"cannot connect to {where}: {exc or type(exc).__name__}"


def _group_of(path: str) -> str:
    try:
        import grp  # POSIX only

        return grp.getgrgid(os.stat(path).st_gid).gr_name
    except (ImportError, OSError, KeyError):
        return ""
