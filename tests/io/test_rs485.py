"""RS-485 direction control (``rtupoll.io.rs485``): the modem-line calls recorded on a
fake port against the bytes written, for a driver with the kernel's RS-485 mode, one with
RTS only, and one with neither."""

from __future__ import annotations

from typing import Any

import pytest

from rtupoll.io import rs485
from rtupoll.io.port_settings import Rs485


class FakePort:
    """Records modem-line calls and bytes written, in order. ``kernel``: the driver
    has RS-485 mode; ``rts``: RTS can be driven."""

    port = "/dev/ttyFAKE0"

    def __init__(self, *, kernel: bool, rts: bool) -> None:
        self.kernel, self.can_rts = kernel, rts
        self.events: list[tuple[str, object]] = []
        self._mode: object = None

    @property
    def rs485_mode(self) -> object:
        return self._mode

    @rs485_mode.setter
    def rs485_mode(self, value: object) -> None:
        if value is not None and not self.kernel:
            raise ValueError("Failed to set RS485 mode: [Errno 25] Inappropriate ioctl")
        self._mode = value
        self.events.append(("rs485_mode", value))

    @property
    def rts(self) -> bool:
        return False

    @rts.setter
    def rts(self, level: bool) -> None:
        if not self.can_rts:
            raise OSError(25, "Inappropriate ioctl for device")
        self.events.append(("rts", level))

    def write(self, data: bytes) -> int:
        self.events.append(("write", data))
        return len(data)

    def flush(self) -> None:
        self.events.append(("flush", None))


def test_kernel_rs485_mode_where_the_driver_has_it() -> None:
    port = FakePort(kernel=True, rts=True)
    mode, toggle = rs485.direction_control(port, Rs485(0.001, 0.002))
    assert mode == "kernel" and toggle is None
    settings: Any = port.rs485_mode
    assert settings.rts_level_for_tx is True and settings.rts_level_for_rx is False
    assert (settings.delay_before_tx, settings.delay_before_rx) == (0.001, 0.002)
    assert [e[0] for e in port.events] == ["rs485_mode"]  # RTS left to the kernel


def test_rts_toggled_around_each_frame_without_kernel_mode() -> None:
    port = FakePort(kernel=False, rts=True)
    mode, toggle = rs485.direction_control(port, Rs485(0.001, 0.002))
    assert mode == "rts" and toggle is not None
    assert port.events == [("rs485_mode", None), ("rts", False)]  # listening
    port.events.clear()
    toggle._sleep = lambda s: port.events.append(("sleep", s))
    frame = bytes.fromhex("02 03 00 02 00 01 25 f9".replace(" ", ""))
    assert toggle.write(port.write, frame) == len(frame)
    assert port.events == [("rts", True), ("sleep", 0.001), ("write", frame),
                           ("flush", None), ("sleep", 0.002), ("rts", False)]


def test_rts_is_dropped_even_when_the_write_fails() -> None:
    port = FakePort(kernel=False, rts=True)
    _, toggle = rs485.direction_control(port, Rs485())
    assert toggle is not None
    port.events.clear()

    def broken(data: bytes) -> int:
        raise OSError(5, "Input/output error")

    with pytest.raises(OSError):
        toggle.write(broken, b"\x01")
    assert port.events == [("rts", True), ("rts", False)]


def test_a_port_with_neither_is_one_clear_line() -> None:
    port = FakePort(kernel=False, rts=False)
    with pytest.raises(Exception) as exc:
        rs485.direction_control(port, Rs485())
    text = str(exc.value)
    assert "\n" not in text and "neither" in text and "RS-485" in text and "RTS" in text
