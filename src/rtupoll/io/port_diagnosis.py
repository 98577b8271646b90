"""Why a port that failed to open failed: pymodbus swallows the error, so after a failed
open the port is tried once more the way pymodbus tries it, and the error is worded by
``rtupoll.io.port_errors``. Used only after a failed open."""

from __future__ import annotations

import contextlib
from typing import Any

from rtupoll.io import own_port
from rtupoll.io.port_errors import gateway_error, open_error
from rtupoll.io.port_names import device_path


def diagnose_serial(url: str, **settings: Any) -> str | None:
    """Try to open ``url`` the way pymodbus does; why it fails, or None if it opens.

    ``url`` may be one of rtupoll's (``nodtr://``: ``rtupoll.io.own_port``'s handlers).
    """
    import serial

    own_port.register()  # nodtr:// and rtupoll:// known to serial_for_url
    try:
        port = serial.serial_for_url(url, exclusive=True, **settings)
    except (OSError, ValueError) as exc:
        return open_error(device_path(url), exc)
    port.close()
    return None


async def diagnose_gateway(host: str, port: int, timeout: float) -> str | None:
    """Try a plain TCP connection; why it fails, or None if it connects."""
    import asyncio

    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    except (TimeoutError, OSError) as exc:
        return gateway_error(host, port, exc, timeout)
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return None
