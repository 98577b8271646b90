"""What a test reads of a pipe it holds without reading it (a reader that stalls)."""

from __future__ import annotations

import fcntl
import termios
import time
from collections.abc import Callable
from subprocess import Popen
from typing import Any

from rtupoll.sim.runner import SimulatedBus


def in_pipe(fd: int) -> int:
    """Bytes in the pipe ``fd`` reads, not yet read."""
    return int.from_bytes(fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"), "little")


def wait_full(fd: int, more: Callable[[], object], *, hang: float = 60.0) -> int:
    """Wait until the pipe ``fd`` reads has stopped filling across two calls of ``more``
    (a wait for more traffic, whose output the writer is given): its writer is blocked
    in a write. A full pipe holds 32-64 KiB, by how the writes fell into its pages, so
    no byte count says it. Its bytes then."""
    deadline = time.monotonic() + hang
    seen, still = -1, 0
    while still < 2:
        assert time.monotonic() < deadline, f"the pipe still fills: {in_pipe(fd)} bytes"
        more()
        now = in_pipe(fd)
        still = still + 1 if now == seen and now > 0 else 0
        seen = now
    return seen


def stall(proc: Popen[Any], bus: SimulatedBus) -> None:
    """Until ``proc``'s stdout pipe, which nobody reads, is full and more of its output
    (of traffic on ``bus``) waits beyond it in its writer's queue."""
    assert proc.stdout is not None

    def more() -> None:  # traffic meanwhile: output queued beyond the pipe
        assert proc.poll() is None, "it ended"
        bus.wait_wire(20, after=bus.wire[-1].time if bus.wire else 0.0, timeout=30)

    wait_full(proc.stdout.fileno(), more)
    more()
