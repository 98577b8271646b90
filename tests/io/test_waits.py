"""The one wait primitive (``rtupoll.io.waits``), chosen by what the port offers: a tty's
descriptor (``FdWait``), a socket (``SocketWait``), or pyserial's own API (``PortWait``:
Windows's ports, ``rfc2217://``, ``socket://``). Each on a real pseudo-terminal or a real
socket; ``PortWait`` is run on a pty too (it needs no descriptor, so it takes one that has
one as well), against the same bytes as ``FdWait``."""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Iterator
from typing import Any

import pytest
import serial
from conftest import ANSWERED

from rtupoll.io import own_port, waits


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    yield master, path
    with contextlib.suppress(OSError):
        os.close(master)


def opened(path: str) -> Any:
    return own_port.Serial(path, baudrate=115200, timeout=waits.SLICE)


def test_the_wait_is_chosen_by_what_the_port_offers(pty: tuple[int, str]) -> None:
    _, path = pty
    port = opened(path)
    a, b = socket.socketpair()
    server = socket.create_server(("127.0.0.1", 0))
    url = serial.serial_for_url(f"socket://127.0.0.1:{server.getsockname()[1]}",
                                timeout=waits.SLICE)
    try:
        assert isinstance(waits.wait_on(port), waits.FdWait)  # a tty: a descriptor
        assert isinstance(waits.wait_on(a), waits.SocketWait)  # recv, never os.read
        assert isinstance(waits.wait_on(url), waits.PortWait)  # its fileno is a socket's
        assert waits.real_fd(url) is None and waits.real_fd(object()) is None
    finally:
        port.close()
        url.close()
        a.close()
        b.close()
        server.close()


@pytest.mark.parametrize("kind", ["fd", "port"])
def test_both_waits_return_what_came_at_once_and_nothing_when_nothing_came(
        pty: tuple[int, str], kind: str) -> None:
    master, path = pty
    port = opened(path)
    try:
        wait = waits.FdWait(port.fileno()) if kind == "fd" else waits.PortWait(port)
        assert wait(0.0) == b""  # nothing waits: nothing, at once
        assert wait(waits.SLICE) == b""  # nothing came within the time
        os.write(master, b"\x03\x04\x02\x01\x02")
        got = b""
        for _ in range(int(ANSWERED / waits.SLICE)):  # (a guard, not a timing claim)
            got += wait(waits.SLICE)
            if len(got) == 5:
                break
        assert got == b"\x03\x04\x02\x01\x02"
        os.write(master, b"\x05")
        got = b""
        for _ in range(int(ANSWERED / waits.SLICE)):
            got += wait(waits.SLICE / 4)  # shorter than a slice: slept, then read
            if got:
                break
        assert got == b"\x05"
    finally:
        port.close()


def test_a_port_gone_is_gone_for_both(pty: tuple[int, str]) -> None:
    master, path = pty
    port = opened(path)
    try:
        os.close(master)  # the other end hung up
        with pytest.raises(waits.Gone):
            waits.FdWait(port.fileno())(waits.SLICE)
        with pytest.raises(waits.Gone):  # (pyserial's read raises on a hung-up tty)
            waits.PortWait(port)(waits.SLICE)
    finally:
        port.close()


def test_a_pump_gives_a_port_with_no_descriptor_one_to_wait_on(pty: tuple[int, str]) -> None:
    """What pymodbus's event loop gets from ``rfc2217://``: a descriptor that is readable
    when bytes came, reads them whole, and says the port is gone when it is."""
    import select

    master, path = pty
    port = opened(path)
    pump = waits.Pump(waits.PortWait(port))
    try:
        assert pump.in_waiting() == 0 and pump.read(64) == b""
        os.write(master, b"\x11\x22\x33")
        got = b""
        while len(got) < 3 and select.select([pump.fileno()], [], [], ANSWERED)[0]:
            got += pump.read(64)
        assert got == b"\x11\x22\x33"
        os.close(master)
        select.select([pump.fileno()], [], [], ANSWERED)
        with pytest.raises(serial.SerialException):
            while True:  # (until the pump has seen the hang-up)
                select.select([pump.fileno()], [], [], ANSWERED)
                pump.read(64)
    finally:
        pump.close()
        port.close()


class _WinePort:
    """pyserial's Windows port as Wine 8.0 runs it: a read whose timeout runs out raises
    ERROR_TIMEOUT (tests/windows/ meet it on a real COM port under Wine)."""

    timeout = waits.SLICE

    def __init__(self, error: str) -> None:
        self.error = error

    def read(self, size: int) -> bytes:
        raise serial.SerialException(self.error)

    @property
    def in_waiting(self) -> int:
        return 0


def test_a_read_that_only_timed_out_under_wine_is_nothing_yet() -> None:
    timed_out = "GetOverlappedResult failed (OSError(22, 'Timeout.', None, 1460))"
    assert waits.PortWait(_WinePort(timed_out))(waits.SLICE) == b""
    with pytest.raises(waits.Gone):  # any other failure is the port's end
        waits.PortWait(_WinePort("ClearCommError failed (OSError(9, 'Invalid handle.', None, "
                                 "6))"))(waits.SLICE)
