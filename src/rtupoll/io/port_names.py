"""A port's name, as the user gives it and as pyserial is given it.

``/dev/ttyUSB0``, ``COM3`` or a pty path is a device; ``tcp://HOST:PORT`` an RTU-over-TCP
gateway (``gateway``); ``rfc2217://`` and ``socket://`` pyserial's serial ports over a
network (``NETWORK``); ``nodtr://PATH`` a device opened with DTR and RTS deasserted; and
``rtupoll://N/PORT`` the name the buses give pymodbus for a port of theirs
(``rtupoll.io.own_port``: ``claim``, the URL handlers). Pure: no port is opened.
"""

from __future__ import annotations

from rtupoll.errors import UsageError

SCHEME = "nodtr"
PREFIX = f"{SCHEME}://"
OWN = "rtupoll"  # rtupoll://N/dev/ttyUSB0: the port of ``own_port.Slot`` N (``claim``)
OWN_PREFIX = f"{OWN}://"
NETWORK = ("rfc2217://", "socket://")  # pyserial's serial ports over a network


def port_url(port: str, *, deassert_dtr: bool) -> str:
    """The URL to give pyserial: ``nodtr://`` for a device path when DTR must stay low.

    Other URLs (``socket://``, ``rfc2217://``) have no modem lines and pass unchanged.
    """
    if deassert_dtr and "://" not in port:
        return PREFIX + port
    return port


def gateway(port: str) -> tuple[str, int] | None:
    """(host, port) of an RTU-over-TCP gateway ``tcp://HOST:PORT``; None for anything else."""
    if not port.lower().startswith("tcp://"):
        return None
    host, _, number = port[6:].rstrip("/").rpartition(":")
    if not host or not number.isdigit() or not 0 < int(number) < 65536:
        raise UsageError(f"{port!r}: expected tcp://HOST:PORT")
    return host.strip("[]"), int(number)


def device_path(port: str) -> str:
    """The filesystem path behind a port, ``nodtr://`` or ``rtupoll://N`` URL."""
    if port.lower().startswith(OWN_PREFIX):
        return port[len(OWN_PREFIX):].partition("/")[2]
    return port[len(PREFIX):] if port.lower().startswith(PREFIX) else port
