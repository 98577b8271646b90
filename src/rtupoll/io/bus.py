"""One RS-485 bus: pymodbus carries the bytes, the sans-IO line discipline decides.

The only module that imports pymodbus, and a thin one: it uses pymodbus's public
transport surface only (docs/architecture.md, "pymodbus": each behaviour relied on is
pinned by tests/io/test_pymodbus_surface.py). pymodbus's transport opens the port (a
serial port through rtupoll's own pyserial URL handler, ``rtupoll://``, so the
``Serial`` object is rtupoll's; or an RTU-over-TCP gateway) and delivers what
arrives. What a transaction does -- checks, attempts, retries, outcome, statistics --
is ``rtupoll.rtu.transaction.Transaction``'s, and every rule of the shared line --
the 3.5-character silence, the drain after a timeout, which received bytes answer
which request (resynchronisation past noise, foreign and late frames, the late-reply
accounting), garbled replies known at once, an adapter's echo -- is
``rtupoll.rtu.line.Line``'s; this module drives them with what went out, what came in
and the line's clock (``rtupoll.io.clock``).

- **One transaction in flight**: the bus's lock spans silence, request, reply and
  retries, so devices polled from several tasks never interleave on the wire. A
  request whose answer could be confused with an earlier request's late reply waits
  (``Line.hazard_until``) *before* taking the lock: other devices go on meanwhile.
- **Silence**: each request goes at ``Line.ready_at``, after a long wait written by a
  timer callback (the waiting task is woken only by the answer). asyncio times in whole
  milliseconds and would overshoot, so the last 2 ms at most are waited in ``select``
  on the port (bytes arriving end it): no CPU, one wake-up, and the event loop held
  for that long (the 3.5-character silence itself above 19200 baud, 1.75 ms). With
  other buses open in the process, whose replies wait while the loop is held, 0.5 ms
  at most (the timer is set 0.5 ms before the end and fires within 1 ms after its
  time, so the frame goes at most 0.5 ms late): ``benchmarks/poll_buses.py``. Bytes
  that arrived meanwhile are taken in before the frame goes, and the silence starts
  again.
- **Timeout and retries per transaction**: each attempt is bounded by the timeout
  plus the frames' wire time (slow baud rates do not eat the device's time); the
  bus retries itself.
- **Receiving**: the transport hands every byte to the line; pymodbus's client, its
  receive buffer, framer and PDU decoder are not used (they drop a buffer on one
  stray byte, and cost CPU the line has already spent).
- **DTR, RS-485 direction**: ``deassert_dtr`` opens the port with DTR and RTS low;
  ``rs485`` drives the transceiver's direction (kernel RS-485 mode, else RTS around
  each frame); both on rtupoll's ``Serial`` (``rtupoll.io.own_port``).
- **Echo**: ``echo`` tells the line that the adapter echoes each request.
- **Reconnect**: pymodbus's reconnect loop is off; a vanished port is reopened by the
  next transaction (``PortError`` while it is gone; the reason -- missing, busy,
  permission, refused, unreachable -- named by ``rtupoll.io.port_diagnosis``).

pymodbus's ``pymodbus`` logger is silenced on import unless the application set a
level on it (``pymodbus_logging`` turns it on).
"""
from __future__ import annotations

import asyncio
import logging
import select
import time
import weakref
from collections.abc import Callable
from typing import Any

import serial
from pymodbus.transport import CommParams, CommType, ModbusProtocol
from pymodbus.transport.serialtransport import SerialTransport

from rtupoll.errors import PortError
from rtupoll.io import clock, own_port, port_diagnosis, port_names, pty_parity, taps
from rtupoll.io.interface import LineBus, raise_failed
from rtupoll.io.latency import latency_timer
from rtupoll.io.port_errors import gateway_error
from rtupoll.io.port_settings import PortSettings
from rtupoll.rtu.line import Line
from rtupoll.rtu.transaction import (
    OUTCOMES,
    BusStats,
    Done,
    Failed,
    Transaction,
)

__all__ = ["OUTCOMES", "Bus", "BusStats", "PortSettings", "pymodbus_logging"]

# a wait for the line this short (at most 1-2 ms) is slept at once: the event loop's timer
# (epoll waits in whole milliseconds) would overshoot it, and wake the process twice where
# once is enough (each wake costs about as much CPU as the transaction's own work)
_SLEEP_MAX = 0.002
# with other buses open in the process, the loop is held for less: the timer, which fires
# within 1 ms after its time, is set 0.5 ms before the silence ends, so the bus holds the
# loop at most 0.5 ms (waking early) or sends at most 0.5 ms late (benchmarks/poll_buses.py:
# 0.93 of each bus's rate alone, against 0.91 holding 1 ms and 0.89 holding none)
_SLEEP_SHARED = 0.0005
_OPEN: weakref.WeakSet[Bus] = weakref.WeakSet()  # the buses open in this process
_HAZARD_POLL = 0.01  # while waiting out a possible late reply, look again this often
_BACKSTOP = 60.0  # pymodbus's own timeout (it never waits for a reply: the line does)
_CHUNK = 1024  # bytes read at most at once (as pymodbus's transport reads)

# pymodbus polls a serial port every 0.5 ms on Windows (``force_poll``, chosen by the
# platform's name: x1.9 the CPU per transaction, benchmarks/portable_wait.py) and waits
# on its descriptor elsewhere. rtupoll's port always offers one to wait on (a tty's, or
# the ``waits.Pump`` of a port that has none: Windows's COM ports, ``rfc2217://``), and
# its loop is the selector loop everywhere (``rtupoll.aio``): the event loop waits.
SerialTransport.force_poll = False

_PYMODBUS_LOG = logging.getLogger("pymodbus")
if _PYMODBUS_LOG.level == logging.NOTSET:  # quiet, unless the application asked for it
    _PYMODBUS_LOG.setLevel(logging.CRITICAL + 1)


def pymodbus_logging(level: int = logging.DEBUG) -> None:
    """Let pymodbus's own log through (``--debug``); it is silent by default."""
    _PYMODBUS_LOG.setLevel(level)


class Bus(LineBus):
    """One port, one master, one transaction at a time. See the module docstring.

    ``drain``: quiet period required after a timeout before the next request
    (None: the length of the timeout that expired). ``broadcast_turnaround``: pause
    after a broadcast so devices can act on it before the next request.
    """

    def __init__(self, settings: PortSettings, *, drain: float | None = None,
                 connect_timeout: float = 3.0, broadcast_turnaround: float = 0.1) -> None:
        self.settings = settings
        self.framing = settings.framing
        self.stats = BusStats()
        self._gateway = settings.gateway
        # pymodbus opens the port by this URL, through rtupoll's pyserial URL handler, so
        # that the Serial object is rtupoll's (``slot.port``) and written to at once
        self._url, self._slot = own_port.claim(settings.port, rs485=settings.rs485,
                                               deassert_dtr=settings.deassert_dtr,
                                               parity=settings.parity)
        self._connect_timeout = connect_timeout
        self.broadcast_turnaround = broadcast_turnaround
        self._lock = asyncio.Lock()
        self._port: _Port | None = None
        self.line = Line(self.framing, drain=drain, echo=settings.echo,
                         idle_gap=settings.idle_gap)
        self.line.tap = taps.tap_for(settings.port, self.framing)
        # a USB-serial adapter's latency timer (Linux sysfs), added to every reply's time
        self.adapter_latency = latency_timer(settings.port) or 0.0
        self._tx: Transaction | None = None  # the transaction whose attempt is in flight
        self._over: asyncio.Future[None] | None = None  # set when that attempt is over
        self._loop: asyncio.AbstractEventLoop | None = None  # the port's, once open

    # -- opening and closing -------------------------------------------------

    async def open(self) -> None:
        """Open the port; ``PortError`` says missing / busy / permission / refused."""
        async with self._lock:
            await self._connect()

    async def close(self) -> None:
        async with self._lock:
            _OPEN.discard(self)
            if self._port is not None:
                self._port.close()
                self._port = None

    async def __aenter__(self) -> Bus:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        return self._port is not None and self._port.is_active()

    def _make_port(self) -> _Port:
        s = self.settings
        common: dict[str, Any] = dict(comm_name=s.port, reconnect_delay=0,
                                      timeout_connect=_BACKSTOP)
        if self._gateway:
            params = CommParams(comm_type=CommType.TCP, host=self._gateway[0],
                                port=self._gateway[1], **common)
        else:
            params = CommParams(comm_type=CommType.SERIAL, host=self._url, baudrate=s.baudrate,
                                bytesize=s.bytesize, stopbits=s.stopbits,
                                parity=pty_parity.line_parity(s.port, s.parity), **common)
        return _Port(params, self._received)

    async def _connect(self) -> None:
        if self.connected:
            return
        if self._port is None:
            self._port = self._make_port()
        why: str | None = None
        try:
            ok = await asyncio.wait_for(self._port.connect(), self._connect_timeout)
        except TimeoutError as exc:
            ok = False
            if self._gateway:  # it does not answer: trying again would only wait again
                why = gateway_error(*self._gateway, exc, self._connect_timeout)
        except Exception:  # pymodbus, pyserial (ValueError: unknown URL)
            ok = False
        if ok and self.connected:
            _OPEN.add(self)
            self._loop = asyncio.get_running_loop()  # the port's callbacks run on it
            self.line.opened(clock.now())  # a fresh port: count the silence from now
            return
        self._port.close()
        self._port = None
        if why is None and self._slot is not None and self._slot.error:
            why = self._slot.error  # it opened, but cannot be used as asked (--rs485)
        if why is None and self._gateway:
            why = await port_diagnosis.diagnose_gateway(*self._gateway, self._connect_timeout)
        elif why is None:
            s = self.settings
            url = port_names.port_url(port_names.device_path(s.port),
                                      deassert_dtr=s.deassert_dtr or
                                      s.port.lower().startswith("nodtr://"))
            why = port_diagnosis.diagnose_serial(url, baudrate=s.baudrate, bytesize=s.bytesize,
                                                 parity=pty_parity.line_parity(s.port, s.parity),
                                                 stopbits=s.stopbits)
        raise PortError(why or f"cannot open {self.settings.port} (it opens now: retry)")

    # -- one transaction (rtu.transaction says what; this drives it) ----------------

    async def _run(self, tx: Transaction) -> Done:
        """``tx`` under the lock, once no earlier request's late reply could be mistaken
        for its answer (waited for without the lock)."""
        while True:
            now = clock.now()
            if tx.hazard_until(now) > now:
                await self._hazard_clear(tx)
            await self._lock.acquire()
            now = clock.now()
            if tx.hazard_until(now) <= now:
                break
            self._lock.release()  # another task's request made one: wait again
        started = now
        outcome: str | None = None
        try:
            while True:  # LineBus._drive and its _step, flat: coroutine frames less per wake-up
                step = tx.next()
                if isinstance(step, Done):
                    return step
                if isinstance(step, Failed):
                    raise_failed(step)
                # an attempt, start to end (``_attempt`` both sends and waits)
                if not self.connected:
                    if tx.attempts:
                        raise PortError(f"{self.settings.port} went away during the "
                                        "transaction")
                    await self._connect()
                await self._attempt(tx)
                if not tx.heard and not self.connected:
                    raise PortError(f"{self.settings.port} went away during the transaction")
        except PortError:
            outcome = "port"
            raise
        finally:
            self.stats.add(tx, clock.now() - started, outcome=outcome)
            self._lock.release()

    async def _hazard_clear(self, tx: Transaction) -> None:
        """Wait (without holding the bus) until no earlier request's late reply could be
        taken for ``tx``'s answer; an arriving answer ends the wait early."""
        while True:
            now = clock.now()
            until = tx.hazard_until(now)
            if until <= now:
                return
            await asyncio.sleep(min(until - now, _HAZARD_POLL))

    async def _attempt(self, tx: Transaction) -> None:
        """One attempt of ``tx``: its request goes once the line lets it go, and this
        returns when the attempt is over (an answer, a garbled reply, its deadline).

        The frame goes as soon as the silence is over: written here after a short sleep,
        or by a timer callback after a long wait, never by this task waking up first (a
        turn of the event loop less per transaction)."""
        if not self.connected:
            raise PortError(f"{self.settings.port} is not open")
        loop = self._loop or asyncio.get_running_loop()  # (asking costs a system call)
        over: asyncio.Future[None] = loop.create_future()
        timer: asyncio.Handle | None = None

        def send() -> None:
            nonlocal timer
            delay = tx.ready_at() - clock.now()
            hold = _SLEEP_MAX if len(_OPEN) < 2 else _SLEEP_SHARED
            if delay > hold:  # the event loop's timer, which fires up to 1 ms late,
                timer = loop.call_later(delay - hold, send)  # for all but the end
                return
            if delay > 0 and self._quiet(delay):  # bytes came: the silence starts again
                timer = loop.call_soon(send)
                return
            if not self.connected:
                over.set_exception(PortError(f"{self.settings.port} went away"))
                return
            try:
                tx.sent(clock.now())
                self._send(tx.request)
            except Exception as exc:  # a callback's error would reach no one: the caller's
                over.set_exception(exc)
                return
            if tx.result is not None:  # a broadcast: over once sent
                over.set_result(None)
            else:
                self._tx, self._over = tx, over
                timer = loop.call_later(tx.deadline - clock.now(), expire)

        def expire() -> None:
            nonlocal timer
            now = clock.now()
            if now < tx.deadline:  # the loop's timer is early (its clock is not the line's)
                timer = loop.call_later(tx.deadline - now, expire)
                return
            tx.expired(now)
            if not over.done():
                over.set_result(None)

        send()
        try:
            await over
        finally:
            if timer is not None:
                timer.cancel()
            self._tx = self._over = None

    def _quiet(self, delay: float) -> bool:
        """Wait the last ``delay`` seconds of the silence, holding the event loop, in
        ``select`` on rtupoll's own ``Serial``: one system call that both waits and sees
        a byte arrive. True when bytes came (they went to the line). A port with no
        descriptor (Windows, ``rfc2217://``, ``socket://``) sleeps, then takes what came
        meanwhile (``rtupoll.io.waits``: stamped late, never early). A gateway keeps the
        silence on its own line: a plain sleep."""
        port = self._slot.port if self._slot is not None else None
        if port is None or not port.is_open:
            time.sleep(delay)
            return False
        fd = port.device_fd
        if fd is None:
            time.sleep(delay)
            return self._took_input()
        try:
            ready, _, _ = select.select([fd], [], [], delay)
        except (OSError, ValueError):  # closed meanwhile: the write that follows says so
            return False
        return bool(ready) and self._took_input()

    def _took_input(self) -> bool:
        """Whether bytes arrived while the event loop slept: they go to the line now, so
        the silence is counted from them (read from rtupoll's own ``Serial``; a gateway
        keeps the silence on its own line)."""
        port = self._slot.port if self._slot is not None else None
        try:  # what waits: one read on the non-blocking port pymodbus's transport made
            if port is None or not port.is_open:
                data = b""
            elif port.timeout == 0 or port.pumped:
                data = port.read(_CHUNK)
            else:  # (a timeout other than 0 would block: then only what waits is asked)
                waiting = port.in_waiting
                data = port.read(waiting) if waiting else b""
        except (OSError, serial.SerialException):  # the write that follows fails too
            return False
        if data:
            self._received(data)
        return bool(data)

    def _send(self, request: bytes) -> None:
        """Put ``request`` on the wire now. pymodbus's serial transport would only queue
        it for the event loop's next turn (registering the port for writing, and
        unregistering it, each time); with nothing queued there, it is written to
        rtupoll's own ``Serial`` at once (what does not fit the port's buffer goes to
        the transport, and a port that fails is closed). A socket writes at once anyway."""
        assert self._port is not None  # _attempt checked
        port = self._slot.port if self._slot is not None else None
        transport = self._port.transport
        if port is None or not port.is_open or not isinstance(transport, asyncio.WriteTransport) \
                or transport.get_write_buffer_size():
            self._port.send(request)
            return
        try:
            sent = port.write(request) or 0
        except (OSError, serial.SerialException):  # the port went away
            self._port.close()
            return
        if sent < len(request):
            self._port.send(request[sent:])

    def _received(self, data: bytes) -> None:
        """What the port received: every byte goes to the line (through the transaction
        in flight, which says when its attempt is over)."""
        tx, now = self._tx, clock.now()
        if tx is None:
            self.line.receive(data, now)
        elif tx.received(data, now):
            over = self._over
            if over is not None and not over.done():
                over.set_result(None)


class _Port(ModbusProtocol):
    """pymodbus's transport (a serial port, or a socket to a gateway) through its public
    surface: ``connect``, ``send``, ``close``, ``is_active`` and the callbacks. Every
    received byte goes to the bus (``callback_data`` consumes all of it): pymodbus's
    framer and transaction manager are not in the way (they drop a buffer on one stray
    byte, and cost CPU)."""

    def __init__(self, params: CommParams, received: Callable[[bytes], None]) -> None:
        super().__init__(params, False)
        self._received = received

    def callback_new_connection(self) -> ModbusProtocol:  # only servers accept connections
        raise NotImplementedError

    def callback_connected(self) -> None:
        pass

    def callback_disconnected(self, exc: Exception | None) -> None:
        pass

    def data_received(self, data: bytes) -> None:
        """asyncio's ``Protocol.data_received``, which pymodbus's transports call with
        every chunk: straight to the bus (pymodbus's receive buffer, its local-echo
        filter and ``callback_data`` cost CPU per chunk, and the line needs none)."""
        self._received(data)

    def callback_data(self, data: bytes, addr: tuple[str, int] | None = None) -> int:
        self._received(data)  # (not called while data_received goes to the bus)
        return len(data)
