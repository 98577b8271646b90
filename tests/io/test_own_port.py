"""rtupoll's own port (``rtupoll.io.own_port``): the ``nodtr://`` and ``rtupoll://`` URL
handlers and the slots behind them; its ``Serial`` on a non-blocking port (timeout 0, as
pymodbus's transport sets it): one ``os.read`` / ``os.write`` per call instead of
pyserial's ``Timeout`` and ``select``, with pyserial's results and errors. On a real
pseudo-terminal."""

from __future__ import annotations

import contextlib
import os
import select
from collections.abc import Iterator

import pytest
import serial
from conftest import ANSWERED

from rtupoll.errors import UsageError
from rtupoll.io import own_port
from rtupoll.io.own_port import Serial
from rtupoll.io.port_settings import Rs485


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal: (the master's fd, the slave's path); the master closed after."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    yield master, path
    with contextlib.suppress(OSError):  # a test closed it
        os.close(master)


def test_nodtr_url_handler() -> None:
    port = serial.serial_for_url("nodtr:///dev/ttyUSB3", do_not_open=True)
    assert isinstance(port, own_port.Serial)
    assert port.port == "/dev/ttyUSB3"


def test_a_claimed_port_is_opened_through_its_slot_until_released() -> None:
    url, slot = own_port.claim("nodtr:///dev/ttyUSB3", deassert_dtr=False, parity="E")
    assert slot is not None and slot.deassert_dtr and slot.parity == "E"  # nodtr:// says so
    assert url.startswith("rtupoll://") and url.endswith("/dev/ttyUSB3")
    port = serial.serial_for_url(url, do_not_open=True)
    assert isinstance(port, own_port.Serial) and port.slot is slot
    assert port.port == "/dev/ttyUSB3"
    own_port.release(url)
    with pytest.raises(serial.SerialException):
        serial.serial_for_url(url, do_not_open=True)


def test_network_ports_get_a_slot_and_other_urls_pass_unchanged() -> None:
    url, slot = own_port.claim("socket://127.0.0.1:7", deassert_dtr=True)
    assert slot is not None and not slot.deassert_dtr  # a network port's modem lines are not ours
    own_port.release(url)
    assert own_port.claim("loop://", deassert_dtr=True) == ("loop://", None)
    with pytest.raises(UsageError, match="not a serial port"):
        own_port.claim("socket://127.0.0.1:7", deassert_dtr=False, rs485=Rs485())


def _port(path: str, **options: object) -> Serial:
    options.setdefault("timeout", 0)
    options.setdefault("write_timeout", 0)
    return Serial(path, baudrate=115200, **options)


def test_what_waits_is_read_whole_and_nothing_waiting_reads_empty(pty: tuple[int, str]) -> None:
    master, path = pty
    port = _port(path)
    try:
        assert port.read(1024) == b""  # nothing waits: empty, no error
        os.write(master, b"\x02\x03\x04\x00\x01\x00\x02")
        select.select([port.fileno()], [], [], ANSWERED)
        assert port.read(1024) == b"\x02\x03\x04\x00\x01\x00\x02"
        os.write(master, b"abcdef")
        select.select([port.fileno()], [], [], ANSWERED)
        assert port.read(4) == b"abcd"  # at most what was asked: the rest waits
        assert port.read(4) == b"ef"
    finally:
        port.close()


def test_a_port_whose_other_end_is_gone_raises_as_pyserial_does(pty: tuple[int, str]) -> None:
    """The other end hung up: the read finds nothing where the port said it was ready;
    rtupoll's port raises what pyserial's own raises for the same port (pymodbus's
    transport closes on it)."""
    master, path = pty
    ours, theirs = _port(path), serial.Serial(path, baudrate=115200, timeout=0)
    try:
        os.close(master)
        with pytest.raises(serial.SerialException) as pyserials:
            theirs.read(1024)
        with pytest.raises(serial.SerialException) as rtupolls:
            ours.read(1024)
        assert str(rtupolls.value) == str(pyserials.value)
        assert "returned no data" in str(rtupolls.value)
    finally:
        ours.close()
        theirs.close()


def test_a_closed_port_is_refused_as_pyserial_refuses_it(pty: tuple[int, str]) -> None:
    _, path = pty
    port = _port(path)
    port.close()
    with pytest.raises(serial.PortNotOpenError):
        port.read(1)
    with pytest.raises(serial.PortNotOpenError):
        port.write(b"x")


def test_a_write_returns_what_fitted_and_never_spins_on_a_full_buffer(
        pty: tuple[int, str]) -> None:
    master, path = pty
    port = _port(path)
    try:
        assert port.write(b"\x01\x03\x00\x00\x00\x01\x84\x0a") == 8
        select.select([master], [], [], ANSWERED)
        assert os.read(master, 64) == b"\x01\x03\x00\x00\x00\x01\x84\x0a"
        chunk, sent = b"\x55" * 4096, []
        for _ in range(1000):  # nobody reads the master: its buffer fills
            sent.append(port.write(chunk))
            if sent[-1] == 0:
                break
        assert sent[-1] == 0  # full: 0 bytes, at once (pyserial would loop until it drains)
        assert sum(sent) > 0
    finally:
        port.close()


def test_a_port_with_a_timeout_keeps_pyserials_blocking_read(pty: tuple[int, str]) -> None:
    """``timeout`` above 0 (not how pymodbus opens it): pyserial's own ``read``, which waits
    for the bytes asked for."""
    master, path = pty
    port = _port(path, timeout=ANSWERED, write_timeout=None)
    try:
        os.write(master, b"ab")
        assert port.read(2) == b"ab"
        assert port.write(b"xyz") == 3
        select.select([master], [], [], ANSWERED)
        assert os.read(master, 8) == b"xyz"
    finally:
        port.close()
