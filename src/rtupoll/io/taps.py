"""Who looks at the buses' own frames (``--traffic``, ``--capture``): one sink for the
process, set by the command that was asked for it, and every bus the process opens
hands its line's bytes to it, named by the bus's port. With no sink nothing is called:
the line's tap is None."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from rtupoll.rtu.timing import Framing


class Sink(Protocol):
    def __call__(self, port: str, framing: Framing, sent: bool, data: bytes) -> None: ...


_sink: Sink | None = None


def listen(sink: Sink | None) -> None:
    """Every bus opened from now on hands its frames to ``sink`` (None: to nobody)."""
    global _sink
    _sink = sink


def tap_for(port: str, framing: Framing) -> Callable[[bool, bytes], None] | None:
    """The tap a bus on ``port`` gives its line: None while nobody listens."""
    sink = _sink
    if sink is None:
        return None

    def tap(sent: bool, data: bytes) -> None:
        sink(port, framing, sent, data)

    return tap
