"""A line's parity on a pseudo-terminal (``rtupoll.io.pty_parity``): opened without, marked
as libmodbus marks it, read back from the other side. On a real pty (POSIX)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator

import pytest

from rtupoll.io.pty_parity import line_parity, pty_parity, pty_parity_of

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="a pty is POSIX's")


@pytest.fixture
def pty() -> Iterator[tuple[int, int]]:
    master, slave = os.openpty()
    yield master, slave
    os.close(master)
    os.close(slave)


def test_a_pty_is_opened_without_parity_and_a_device_with_it(pty: tuple[int, int]) -> None:
    path = os.ttyname(pty[1])
    assert line_parity(path, "E") == "N"
    assert line_parity(f"nodtr://{path}", "O") == "N"
    assert line_parity("/dev/ttyUSB0", "E") == "E"


@pytest.mark.parametrize("parity", ["E", "O"])
def test_the_mark_is_read_back_from_the_other_side(pty: tuple[int, int], parity: str) -> None:
    master, slave = pty
    assert pty_parity_of(master) == "N"
    pty_parity(slave, parity)
    assert pty_parity_of(master) == parity


def test_a_closed_descriptor_is_no_error_and_no_parity() -> None:
    master, slave = os.openpty()
    os.close(master)
    os.close(slave)
    pty_parity(slave, "E")  # best effort: nothing raised
    assert pty_parity_of(slave) == "N"
