"""Why a port failed to open (``rtupoll.io.port_diagnosis``): tried once more, as pymodbus
tries it, and worded by ``port_errors``; None when it opens after all."""

from __future__ import annotations

import asyncio
import os
import socket
import sys
from pathlib import Path

import pytest

from rtupoll.io.port_diagnosis import diagnose_gateway, diagnose_serial


def test_a_missing_port_says_so(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyUSB9")
    why = diagnose_serial(f"nodtr://{path}", baudrate=9600)
    assert why is not None and why.startswith(f"{path} does not exist")


@pytest.mark.skipif(sys.platform == "win32", reason="a pty is POSIX's")
def test_a_port_that_opens_is_no_reason() -> None:
    master, slave = os.openpty()
    try:
        assert diagnose_serial(os.ttyname(slave), baudrate=9600) is None
    finally:
        os.close(master)
        os.close(slave)


def test_a_gateway_that_refuses_says_so() -> None:
    with socket.socket() as s:  # a port nobody listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        why = asyncio.run(diagnose_gateway("127.0.0.1", port, 5.0))
    assert why is not None and "refused the connection" in why


def test_a_gateway_that_accepts_is_no_reason() -> None:
    async def go() -> str | None:
        server = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", 0)
        async with server:
            port = server.sockets[0].getsockname()[1]
            return await diagnose_gateway("127.0.0.1", port, 5.0)
    assert asyncio.run(go()) is None
