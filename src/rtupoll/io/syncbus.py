"""The bus for one-shot commands: the same transaction, driven by blocking I/O.

``rtupoll read`` asks a device once and exits, so it needs no event loop and no
async transport: this driver does what ``rtupoll.rtu.transaction.Transaction``
says with pyserial's ``Serial`` (opened through ``rtupoll.io.serialport``, so DTR,
``--rs485`` and the error wording are the port's own) or a plain socket to an
RTU-over-TCP gateway, waiting in ``select`` and reading ``time.monotonic()``. The
rules -- checks, attempts, retries, the silence, the drain, resynchronisation, late
replies, statistics -- are the same objects the async ``rtupoll.io.bus.Bus`` drives
(``LineBus``, ``Transaction``, ``Line``); only the waiting differs. It imports
neither asyncio nor pymodbus, which is most of what a one-shot read used to pay for
before it sent a byte (benchmarks/README.md, read_vs_mbpoll.py).

Its methods are ``BusLike``'s coroutines, so the jobs written for any bus
(``jobs.holes.read_all``, ``jobs.device.probe_variant``) run on it unchanged; they
never suspend, because nothing here awaits, and ``run`` drives such a coroutine to
its end without an event loop. A job that awaits anything else (a sleep, a task) is
a programming error, said at once (``RuntimeError``), not a hang.

- **Silence and deadlines** are waited for in ``select``, whose timeout has
  microseconds (asyncio's timers have milliseconds), so the request goes at
  ``Line.ready_at`` exactly; bytes that arrive meanwhile go to the line, and the
  silence starts again.
- **A port that goes away** (the read fails, or ends) is closed: ``PortError``, as
  the async bus says it.
"""

from __future__ import annotations

import contextlib
import os
import select
import time
from collections.abc import Awaitable
from typing import Any, TypeVar

from rtupoll.errors import PortError
from rtupoll.io import serialport
from rtupoll.io.interface import LineBus
from rtupoll.io.serialport import PortSettings
from rtupoll.rtu.line import Line
from rtupoll.rtu.transaction import Await, BusStats, Done, Send, Transaction

T = TypeVar("T")

_CHUNK = 4096


def run(job: Awaitable[T]) -> T:
    """The result of ``job``, a coroutine that never suspends (one on a ``SyncBus``)."""
    steps = job.__await__()
    try:
        steps.send(None)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]
    close = getattr(steps, "close", None)
    if close is not None:
        close()
    raise RuntimeError("a job on the blocking bus awaited something else (only the bus's "
                       "own methods may be awaited)")


class SyncBus(LineBus):
    """One port, one master, blocking: ``Bus``'s transactions without an event loop.
    See the module docstring; ``drain`` and ``broadcast_turnaround`` as ``Bus``'s."""

    def __init__(self, settings: PortSettings, *, drain: float | None = None,
                 connect_timeout: float = 3.0, broadcast_turnaround: float = 0.1) -> None:
        self.settings = settings
        self.framing = settings.framing
        self.stats = BusStats()
        self.broadcast_turnaround = broadcast_turnaround
        self.line = Line(self.framing, drain=drain, echo=settings.echo,
                         idle_gap=settings.idle_gap)
        self.adapter_latency = serialport.latency_timer(settings.port) or 0.0
        self._gateway = settings.gateway
        self._url, self._slot = serialport.claim(settings.port, rs485=settings.rs485,
                                                 deassert_dtr=settings.deassert_dtr,
                                                 parity=settings.parity)
        self._connect_timeout = connect_timeout
        self._port: Any = None  # pyserial's Serial, or a socket to a gateway
        self._fd = -1

    # -- opening and closing -------------------------------------------------

    def __enter__(self) -> SyncBus:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    async def open(self) -> None:
        self.connect()

    async def close(self) -> None:
        self.disconnect()

    @property
    def connected(self) -> bool:
        return self._port is not None

    def connect(self) -> None:
        """Open the port; ``PortError`` says missing / busy / permission / refused."""
        if self._port is not None:
            return
        if self._gateway:
            self._port = self._open_gateway(*self._gateway)
            self._port.setblocking(False)
        else:
            self._port = self._open_serial()
        self._fd = self._port.fileno()
        self.line.opened(time.monotonic())  # a fresh port: count the silence from now

    def disconnect(self) -> None:
        port, self._port, self._fd = self._port, None, -1
        if port is not None:
            with contextlib.suppress(OSError):
                port.close()

    def _open_serial(self) -> Any:
        import serial

        s = self.settings
        try:
            return serial.serial_for_url(
                self._url, exclusive=True, baudrate=s.baudrate, bytesize=s.bytesize,
                parity=serialport.line_parity(s.port, s.parity), stopbits=s.stopbits,
                timeout=0)
        except (OSError, ValueError) as exc:  # SerialException is an OSError
            if self._slot is not None and self._slot.error:
                raise PortError(self._slot.error) from None  # opens, but not as asked
            raise PortError(serialport.open_error(self._url, exc)) from None

    def _open_gateway(self, host: str, port: int) -> Any:
        import socket

        try:
            return socket.create_connection((host, port), timeout=self._connect_timeout)
        except OSError as exc:  # refused, unreachable, unresolved, timed out
            raise PortError(serialport.gateway_error(host, port, exc,
                                                     self._connect_timeout)) from None

    # -- one transaction (rtu.transaction says what; this drives it) ----------------

    async def _run(self, tx: Transaction) -> Done:
        self._wait_hazard(tx)
        started = time.monotonic()
        outcome: str | None = None
        try:
            return await self._drive(tx)
        except PortError:
            outcome = "port"
            raise
        finally:
            self.stats.add(tx, time.monotonic() - started, outcome=outcome)

    async def _step(self, tx: Transaction, step: Send | Await) -> None:
        if isinstance(step, Await):
            self._wait(tx, step.until, ending=True)
            return
        if tx.attempts and not self.connected:
            raise PortError(f"{self.settings.port} went away during the transaction")
        self.connect()
        if self._wait(tx, step.at, ending=False):
            return  # bytes came meanwhile: the silence starts again (ask next() again)
        tx.sent(time.monotonic())
        self._write(step.frame)

    def _wait_hazard(self, tx: Transaction) -> None:
        """Until no earlier request's late reply could be taken for ``tx``'s answer
        (bytes that arrive meanwhile go to the line, and may end the wait early)."""
        now = time.monotonic()
        while (until := tx.hazard_until(now)) > now:
            if self.connected:
                self._wait(tx, until, ending=False)
            else:
                time.sleep(until - now)
            now = time.monotonic()

    def _wait(self, tx: Transaction, until: float, *, ending: bool) -> bool:
        """Take in what arrives until ``until``: True when bytes came (``ending``: when
        they ended the attempt in flight); at ``until`` of an attempt, it expires."""
        while True:
            now = time.monotonic()
            left = until - now
            if left <= 0:
                if ending:
                    tx.expired(now)
                return False
            ready, _, _ = select.select([self._fd], [], [], left)
            if not ready:
                continue
            data = self._read()
            if not data:  # nothing after all (the port is non-blocking)
                continue
            over = tx.received(data, time.monotonic())
            if not ending or over:
                return True

    def _read(self) -> bytes:
        try:
            data = os.read(self._fd, _CHUNK)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:  # the port (or the gateway's connection) is gone
            self.disconnect()
            raise PortError(f"{self.settings.port} went away during the transaction")
        return data

    def _write(self, frame: bytes) -> None:
        try:
            if self._gateway:
                self._port.sendall(frame)
            else:
                self._port.write(frame)
        except OSError:  # SerialException too
            self.disconnect()
            raise PortError(f"{self.settings.port} went away during the transaction"
                            ) from None
