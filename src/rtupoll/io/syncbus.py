"""The bus for one-shot commands: the same transaction, driven by blocking I/O.

``rtupoll read`` asks a device once and exits, so it needs no event loop and no
async transport: this driver does what ``rtupoll.rtu.transaction.Transaction``
says with pyserial's ``Serial`` (opened through ``rtupoll.io.own_port``, so DTR,
``--rs485`` and the error wording are the port's own) or a plain socket to an
RTU-over-TCP gateway, waiting in ``rtupoll.io.waits`` and reading the line's clock. The
rules -- checks, attempts, retries, the silence, the drain, resynchronisation, late
replies, statistics -- are the same objects the async ``rtupoll.io.bus.Bus`` drives
(``LineBus``, ``Transaction``, ``Line``); only the waiting differs. It imports
neither asyncio nor pymodbus, which is most of what a one-shot read used to pay for
before it sent a byte (benchmarks/README.md, read_vs_mbpoll.py).

Its methods are ``BusLike``'s coroutines, so the jobs written for any bus
(``jobs.device.read_fields``, ``jobs.device.probe_variant``) run on it unchanged; they
never suspend, because nothing here awaits, and ``run`` drives such a coroutine to
its end without an event loop. A job that awaits anything else (a sleep, a task) is
a programming error, said at once (``RuntimeError``), not a hang.

- **Silence and deadlines** are waited for in the port's ``rtupoll.io.waits.Wait``
  (``select`` on a tty or a socket, whose timeout has microseconds; pyserial's own
  ``read`` on a port with no descriptor: Windows, ``rfc2217://``, ``socket://``), so the
  request goes at ``Line.ready_at``; bytes that arrive meanwhile go to the line, and
  the silence starts again.
- **A port that goes away** (the read fails, or ends) is closed: ``PortError``, as
  the async bus says it.
"""

from __future__ import annotations

import contextlib
import struct
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from rtupoll.errors import PortError
from rtupoll.io import clock as line_clock
from rtupoll.io import own_port, port_names, pty_parity, taps, waits
from rtupoll.io.interface import LineBus
from rtupoll.io.latency import latency_timer
from rtupoll.io.port_settings import PortSettings
from rtupoll.rtu.line import Line
from rtupoll.rtu.transaction import Await, BusStats, Done, Send, Transaction

T = TypeVar("T")



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
                 connect_timeout: float = 3.0, broadcast_turnaround: float = 0.1,
                 clock: Callable[[], float] | None = None,
                 sleep: Callable[[float], None] = time.sleep, opened: Any = None) -> None:
        """``clock``: the line's (``rtupoll.io.clock.now``); ``sleep`` and ``opened`` (a
        port already open, driven instead of opening ``settings.port``): for tests in
        virtual time, with ``clock``."""
        self._clock = clock or line_clock.now
        self._sleep, self._opened = sleep, opened
        self.settings = settings
        self.framing = settings.framing
        self.stats = BusStats()
        self.broadcast_turnaround = broadcast_turnaround
        self.line = Line(self.framing, drain=drain, echo=settings.echo,
                         idle_gap=settings.idle_gap)
        self.line.tap = taps.tap_for(settings.port, self.framing)
        self.adapter_latency = latency_timer(settings.port) or 0.0
        self._gateway = settings.gateway
        self._url, self._slot = own_port.claim(settings.port, rs485=settings.rs485,
                                               deassert_dtr=settings.deassert_dtr,
                                               parity=settings.parity)
        self._connect_timeout = connect_timeout
        self._port: Any = None  # pyserial's Serial, or a socket to a gateway
        self._take: waits.Wait | None = None  # the port's wait (rtupoll.io.waits)

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
        if self._opened is not None:
            self._port = self._opened
        elif self._gateway:
            self._port = self._open_gateway(*self._gateway)
            self._port.setblocking(False)
        else:
            self._port = self._open_serial()
        self._take = waits.wait_on(self._port, sleep=self._sleep)
        self.line.opened(self._clock())  # a fresh port: count the silence from now

    def rs485_mode(self) -> str:
        """What the open port says of the kernel's RS-485 mode (Linux, TIOCGRS485):
        "on" (the driver switches the transceiver's direction), "off" (it could), "none"
        (no such mode: a pty, most USB adapters, which switch by themselves), or
        "network" for a gateway or a port reached over the network."""
        if self._gateway or not hasattr(self._port, "fileno"):
            return "network"
        try:
            fd = self._port.fileno()
        except (OSError, ValueError, AttributeError):
            return "network" if "://" in self.settings.port else "none"
        try:
            import fcntl
            import termios

            request = getattr(termios, "TIOCGRS485", 0x542E)
            flags = struct.unpack("8I", fcntl.ioctl(fd, request, bytes(32)))[0]
        except (ImportError, OSError):
            return "none"
        return "on" if flags & 1 else "off"

    def disconnect(self) -> None:
        port, self._port, self._take = self._port, None, None
        if port is not None:
            with contextlib.suppress(OSError):
                port.close()

    def _open_serial(self) -> Any:
        import serial

        s = self.settings
        try:
            return serial.serial_for_url(
                self._url, exclusive=True, baudrate=s.baudrate, bytesize=s.bytesize,
                parity=pty_parity.line_parity(s.port, s.parity), stopbits=s.stopbits,
                timeout=waits.SLICE)  # (PortWait's; FdWait reads the descriptor itself)
        except (OSError, ValueError) as exc:  # SerialException is an OSError
            from rtupoll.io.port_errors import open_error

            if self._slot is not None and self._slot.error:
                raise PortError(self._slot.error) from None  # opens, but not as asked
            raise PortError(open_error(port_names.device_path(self._url), exc)) from None

    def _open_gateway(self, host: str, port: int) -> Any:
        import socket

        try:
            return socket.create_connection((host, port), timeout=self._connect_timeout)
        except OSError as exc:  # refused, unreachable, unresolved, timed out
            from rtupoll.io.port_errors import gateway_error

            raise PortError(gateway_error(host, port, exc,
                                                     self._connect_timeout)) from None

    # -- one transaction (rtu.transaction says what; this drives it) ----------------

    async def _run(self, tx: Transaction) -> Done:
        self._wait_hazard(tx)
        started = self._clock()
        outcome: str | None = None
        try:
            return await self._drive(tx)
        except PortError:
            outcome = "port"
            raise
        finally:
            self.stats.add(tx, self._clock() - started, outcome=outcome)

    async def _step(self, tx: Transaction, step: Send | Await) -> None:
        if isinstance(step, Await):
            self._wait(tx, step.until, ending=True)
            return
        if tx.attempts and not self.connected:
            raise PortError(f"{self.settings.port} went away during the transaction")
        self.connect()
        if self._wait(tx, step.at, ending=False):
            return  # bytes came meanwhile: the silence starts again (ask next() again)
        tx.sent(self._clock())
        self._write(step.frame)

    def _wait_hazard(self, tx: Transaction) -> None:
        """Until no earlier request's late reply could be taken for ``tx``'s answer
        (bytes that arrive meanwhile go to the line, and may end the wait early)."""
        now = self._clock()
        while (until := tx.hazard_until(now)) > now:
            if self.connected:
                self._wait(tx, until, ending=False)
            else:
                self._sleep(until - now)
            now = self._clock()

    def _wait(self, tx: Transaction, until: float, *, ending: bool) -> bool:
        """Take in what arrives until ``until``: True when bytes came (``ending``: when
        they ended the attempt in flight); at ``until`` of an attempt, it expires."""
        while True:
            now = self._clock()
            left = until - now
            if left <= 0:
                if ending:
                    tx.expired(now)
                return False
            data = self._read(left)
            if not data:
                continue
            over = tx.received(data, self._clock())
            if not ending or over:
                return True

    def _read(self, left: float) -> bytes:
        """What arrives within ``left`` seconds; the port (or the gateway's connection)
        gone: closed, and ``PortError``."""
        assert self._take is not None  # connected
        try:
            return self._take(left)
        except waits.Gone:
            self.disconnect()
            raise PortError(f"{self.settings.port} went away during the transaction"
                            ) from None

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
