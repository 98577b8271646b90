"""The tap: a serial port opened for listening only.

pyserial directly, used read-only: this module never calls ``write``, and the port is
opened with DTR and RTS deasserted (``io.own_port.OwnPort``), because on adapters
whose RS-485 driver is enabled by RTS an asserted RTS would put the sniffer's
transmitter on the pair and jam the bus. The adapter's transmitter must stay off
(docs/sniff.md): an adapter with automatic direction control only transmits when
written to, which this never does.

Arrival times are wall-clock seconds since the epoch, taken from the line's clock
(``rtupoll.io.clock``: monotonic, and fine enough to tell frames apart by their
silence) plus the wall time at opening.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

from rtupoll.errors import PortError, UsageError
from rtupoll.io import clock as line_clock
from rtupoll.io import waits
from rtupoll.io.own_port import own_class
from rtupoll.io.port_errors import open_error
from rtupoll.io.port_names import NETWORK, gateway
from rtupoll.rtu.timing import Framing

POLL = 0.02  # seconds between ticks while the line is quiet


class ListenPort:
    """A serial port that is only ever read from."""

    def __init__(self, path: str, framing: Framing) -> None:
        if gateway(path) is not None or ("://" in path and
                                         not path.lower().startswith(NETWORK)):
            raise UsageError(f"{path}: sniff listens on a serial port (an RS-485 adapter on "
                             "the pair, or one served by rfc2217:// or socket://); a TCP "
                             "gateway only shows its own master's traffic")
        port: Any = own_class(path, None)()
        port.port = path
        port.baudrate = framing.baudrate
        port.bytesize = framing.bytesize
        port.parity = framing.parity
        port.stopbits = framing.stopbits
        port.timeout = waits.SLICE  # (PortWait's: a port with no descriptor, Windows's)
        port.exclusive = True
        try:
            port.open()
        except (OSError, ValueError) as exc:
            raise PortError(open_error(path, exc)) from None
        self.path, self._port = path, port
        self._take = waits.wait_on(port)
        mono, wall = line_clock.now(), time.time()
        self.clock: Callable[[], float] = lambda: wall + (line_clock.now() - mono)

    def chunks(self, stop: Callable[[], bool]) -> Iterator[tuple[bytes, float]]:
        """``(bytes, arrival)`` as they come; ``(b"", now)`` every ``POLL`` s of quiet."""
        while not stop():
            try:
                data = self._take(POLL)
            except waits.Gone as exc:
                raise PortError(f"{self.path}: {exc} (adapter unplugged?)") from None
            yield data, self.clock()

    def close(self) -> None:
        self._port.close()
