"""RS-485 direction control on an open port (``--rs485``): the kernel's RS-485 mode
(TIOCSRS485) where the driver has it, else RTS toggled around each write
(``RtsToggle``); a port with neither is a one-line error. rtupoll's own port
(``rtupoll.io.own_port.OwnPort``) sets it up on open."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

import serial
import serial.rs485

from rtupoll.errors import UsageError
from rtupoll.io.port_settings import Rs485


class RtsToggle:
    """RTS driven around each write, for a driver without kernel RS-485 mode: up,
    ``before``, the frame, wait until its last bit has left (``flush``: tcdrain),
    ``after``, down. ``port`` is any object with pyserial's ``rts`` and ``flush``."""

    def __init__(self, port: Any, rs485: Rs485,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.port, self.rs485, self._sleep = port, rs485, sleep

    def write(self, write: Callable[[bytes], int | None], data: bytes) -> int | None:
        self.port.rts = True
        if self.rs485.before:
            self._sleep(self.rs485.before)
        try:
            sent = write(data)
            self.port.flush()
            if self.rs485.after:
                self._sleep(self.rs485.after)
        finally:
            self.port.rts = False
        return sent


def direction_control(port: Any, rs485: Rs485) -> tuple[str, RtsToggle | None]:
    """Set up ``rs485`` on an open ``port``: ("kernel", None) when the driver does it,
    ("rts", the toggler) when RTS can be driven instead; ``UsageError`` (one line) when
    the port can do neither."""
    name = getattr(port, "port", None) or "the port"
    try:
        port.rs485_mode = serial.rs485.RS485Settings(
            rts_level_for_tx=True, rts_level_for_rx=False,
            delay_before_tx=rs485.before, delay_before_rx=rs485.after)
        return "kernel", None
    except (ValueError, OSError, serial.SerialException, NotImplementedError) as exc:
        kernel = str(exc) or type(exc).__name__
        with contextlib.suppress(Exception):
            port.rs485_mode = None
    try:
        port.rts = False  # receiving: the transceiver listens
    except (ValueError, OSError, serial.SerialException) as exc:
        raise UsageError(f"{name} supports neither the kernel's RS-485 mode ({kernel}) nor "
                         f"RTS control ({exc or type(exc).__name__}): --rs485 needs a UART "
                         "with RTS wired to the transceiver's DE/RE, or an adapter that "
                         "switches direction by itself (then leave --rs485 out)") from None
    return "rts", RtsToggle(port, rs485)
