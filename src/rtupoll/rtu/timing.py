"""Serial character timing: how long bytes take on the wire, and the 3.5-character silence."""

from __future__ import annotations

from functools import cached_property

from rtupoll.frozen import frozen


@frozen
class Framing:
    """Serial character framing, for timing: 1 start bit + data + parity + stop bits."""

    baudrate: int
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1

    @property
    def bits_per_char(self) -> float:
        return 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits

    @cached_property  # on every transaction's path: computed once per framing
    def char_time(self) -> float:
        return self.bits_per_char / self.baudrate

    @cached_property
    def silence(self) -> float:
        """Inter-frame silence t3.5; the spec fixes it at 1.75 ms above 19200 baud."""
        return 0.00175 if self.baudrate > 19200 else 3.5 * self.char_time

    def wire_time(self, nbytes: int) -> float:
        return nbytes * self.char_time


def transaction_wire_time(framing: Framing, request: int, response: int) -> float:
    """The least time one transaction holds the bus: both frames plus two silences."""
    return framing.wire_time(request + response) + 2 * framing.silence
