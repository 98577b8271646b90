"""A simulated bus running in the background of this process.

Synchronous tests, CLI subprocesses (``rtupoll read --port PTY``) and ``rtupoll poll
--simulate`` all need a bus that runs while they do something else, so the simulator
runs in a thread with its own event loop. Every running bus is registered here, so the
test suite can fail a test that forgets to stop one (``tests/conftest.py``)::

    with simulated_bus(["net-irnet-pro@1", "huiwen-aq@3"], faults=("3:dead",)) as sim:
        sim.port                             # /dev/pts/N, or tcp://127.0.0.1:PORT
        sim.set(1, "concentration", 12.5)    # pin a value
        sim.get(1, "concentration").value    # 12.5
        sim.wire                             # the latest WireFrames (time, direction, data, note)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import TypeVar

from rtupoll.io import clock as line_clock
from rtupoll.model.codec import Value
from rtupoll.model.interpret import FieldValue
from rtupoll.rtu import Framing, Table
from rtupoll.sim.consistent import make_consistent
from rtupoll.sim.device import SimDevice, SimDeviceConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import (
    DEFAULT_DEVICES,
    Scenario,
    build,
    parse_device,
    profile,
    split_lines,
)
from rtupoll.sim.server import Server, WireFrame
from rtupoll.sim.values import Static

T = TypeVar("T")
# the devices a bus holds when none are named: (profile id, address) pairs
SEED_DEVICES: tuple[tuple[str, int], ...] = tuple(parse_device(d) for d in DEFAULT_DEVICES)
_RUNNING: set[SimulatedBus] = set()
_RUNNING_LOCK = threading.Lock()


def running() -> list[SimulatedBus]:
    """Every simulated bus started and not yet stopped in this process."""
    with _RUNNING_LOCK:
        return list(_RUNNING)


class _LineServer(Server):
    """A server whose pty answers only clients at the line's speed, timed or not.

    Without wire timing a reply still goes out at once, but a client that opened the
    port at another speed gets silence, as from a real line: so ``scan`` finds each
    device at its line's speed only, and a wrong ``--baudrate`` fails as in the field.
    """

    def __init__(self, engine: Engine, *, speed: int | None, framing: Framing | None,
                 on_wire: Callable[[WireFrame], None] | None) -> None:
        super().__init__(engine, framing=framing, on_wire=on_wire)
        self.speed = speed

    def _line_mismatch(self, fd: int) -> str | None:
        if self.speed is None or self.framing is not None:
            return super()._line_mismatch(fd)
        import termios  # (a pty's: POSIX only)

        ospeed = termios.tcgetattr(fd)[5]
        if ospeed != getattr(termios, f"B{self.speed}", ospeed):
            return f"sent at another baud rate than the line's {self.speed}"
        return None


class SimulatedBus:
    """A bus of simulated devices served on a pty (or TCP) from a background thread."""

    def __init__(self, config: Scenario, *, tcp: bool | str = False, link: str | None = None,
                 on_wire: Callable[[WireFrame], None] | None = None, tap: str | None = None,
                 engine: Engine | None = None) -> None:
        """``tap``: also offer a pty, linked there, that hears every byte on the line;
        ``engine``: serve this one (e.g. ``sim.replay``) instead of the config's devices."""
        self.config, self.tcp, self.link, self.on_wire = config, tcp, link, on_wire
        self.echo = False  # an echoing adapter: the master hears each request back
        self.framing = Framing(config.baudrate) if config.baudrate else None
        self.port = ""
        self.tap, self.tap_port = tap, ""
        self.engine: Engine | None = None
        self._given = engine
        self._server: Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # -- life cycle ---------------------------------------------------------
    def start(self) -> SimulatedBus:
        if self._thread is not None:
            raise RuntimeError("this simulated bus was already started")
        c = self.config
        self.engine = self._given or Engine(c.devices, c.faults, seed=c.seed, tick=c.tick,
                                            start=line_clock.now())
        for d in self.engine.devices:
            _consistent(d, c.line_speed)
        self._thread = threading.Thread(target=self._run, name=f"rtupoll-sim-{id(self):x}",
                                        daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error
        with _RUNNING_LOCK:
            _RUNNING.add(self)
        return self

    def stop(self) -> None:
        """Stop serving, close the pty/socket and join the thread. Idempotent."""
        thread, loop, stop = self._thread, self._loop, self._stop
        if thread is not None and thread.is_alive() and loop is not None and stop is not None:
            if not loop.is_closed():  # closed: the thread is ending (stopped from elsewhere)
                with contextlib.suppress(RuntimeError):  # it closed since the check
                    loop.call_soon_threadsafe(stop.set)
            thread.join(timeout=10)
        with _RUNNING_LOCK:
            _RUNNING.discard(self)

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def __enter__(self) -> SimulatedBus:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._main())
        finally:
            loop.close()

    async def _main(self) -> None:
        assert self.engine is not None
        try:
            server = self._server = _LineServer(self.engine, speed=self.config.speed,
                                                framing=self.framing, on_wire=self.on_wire)
            server.echo = self.echo
            if self.tcp:
                host, _, port = (self.tcp if isinstance(self.tcp, str) else "").rpartition(":")
                self.port = await server.serve_tcp(host or "127.0.0.1", int(port or 0))
            else:
                self.port = await server.serve_pty(self.link)
            if self.tap:
                self.tap_port = await server.serve_tap(self.tap)
        except BaseException as exc:
            self._error = exc
            if self._server is not None:
                await self._server.close()
            self._ready.set()
            return
        self._stop = asyncio.Event()
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            await server.close()

    def _call(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` on the simulator's thread (the engine is only touched there)."""
        if self._loop is None or not self.alive or threading.current_thread() is self._thread:
            return fn()
        future: concurrent.futures.Future[T] = concurrent.futures.Future()

        def run() -> None:
            try:
                future.set_result(fn())
            except BaseException as exc:
                future.set_exception(exc)

        self._loop.call_soon_threadsafe(run)
        return future.result(timeout=10)

    # -- looking in and changing things -------------------------------------
    def device(self, unit: int) -> SimDevice:
        """The device now at ``unit`` (or configured there before an address change)."""
        assert self.engine is not None, "start the bus first"
        return self.engine.device(unit)

    def set(self, unit: int, field: str, value: Value) -> None:
        """Pin a field of the device at ``unit`` to ``value`` (it stops moving); fields
        that follow it (``sim.consistent``) follow at once."""
        def pin() -> None:
            d = self.device(unit)
            d.pin(field, value)
            d.advance(0)
        self._call(pin)

    def get(self, unit: int, field: str) -> FieldValue:
        """What the device at ``unit`` would answer for ``field`` now."""
        def read() -> FieldValue:
            d = self.device(unit)
            d.catch_up(line_clock.now())
            return d.value(field)
        return self._call(read)

    def registers(self, unit: int, table: Table | str, address: int, count: int
                  ) -> tuple[int, ...]:
        """The device's register image (wire addresses), without the side effects of a read."""
        return self._call(lambda: self.device(unit).words(Table(table), address, count))

    def advance(self, ticks: int = 1) -> None:
        """Move every unpinned value ``ticks`` steps now (instead of waiting for time)."""
        def step() -> None:
            for d in self.device_list():
                d.advance(ticks)
        self._call(step)

    def connect(self, device: str, profile_dirs: Iterable[Path] = ()) -> SimDevice:
        """Wire one more device (``PROFILE@ADDRESS``) onto the running bus, as a technician
        plugs in a factory-fresh sensor during commissioning."""
        pid, address = parse_device(device)
        config = SimDeviceConfig(profile(pid, profile_dirs), address)

        def add() -> SimDevice:
            assert self.engine is not None, "start the bus first"
            new = SimDevice(config, seed=self.config.seed, tick=self.config.tick,
                            start=line_clock.now())
            _consistent(new, self.config.line_speed)
            self.engine.devices.append(new)
            return new
        return self._call(add)

    def device_list(self) -> list[SimDevice]:
        assert self.engine is not None, "start the bus first"
        return list(self.engine.devices)

    def addresses(self) -> dict[str, int]:
        """Each device (as configured, ``PROFILE@ADDRESS``) -> the address it has now."""
        return self._call(lambda: {d.config.name: d.address for d in self.device_list()})

    @property
    def wire(self) -> tuple[WireFrame, ...]:
        """The latest frames on the wire (up to ``server.WIRE_LOG``), oldest first."""
        if self._server is None:
            return ()
        with self._server.wire_lock:
            return tuple(self._server.wire)

    def wait_wire(self, count: int = 1, *, direction: str = "out", timeout: float = 2.0,
                  after: float = 0.0) -> list[WireFrame]:
        """Wait until ``count`` frames in ``direction`` newer than ``after`` are logged."""
        deadline = time.monotonic() + timeout
        while True:
            got = [w for w in self.wire if w.direction == direction and w.time > after]
            if len(got) >= count or time.monotonic() > deadline:
                return got
            time.sleep(0.002)


def _consistent(d: SimDevice, speed: int | None) -> None:
    """Related fields of a new device agree (``sim.consistent``), rendered into its image."""
    changed = make_consistent(d.profile, d.fields, d.motions, tuple(d.config.pins), d.rng,
                              speed, d.tick or 1.0)
    for name in changed:
        m = d.motions[name]
        if isinstance(m, Static):
            d.pin(name, m.value)
    d.advance(0)


def simulated_bus(devices: Sequence[str] = (), *, baudrate: int | None = None,
                  faults: Sequence[str] = (), scenario: str | Path | None = None,
                  tcp: bool | str = False, seed: int | None = None, sets: Sequence[str] = (),
                  options: Sequence[str] = (), turnaround: float | None = None,
                  tick: float | None = 1.0, profile_dirs: Iterable[Path] = (),
                  link: str | None = None,
                  on_wire: Callable[[WireFrame], None] | None = None,
                  tap: str | None = None) -> SimulatedBus:
    """A simulated bus, started by ``with`` (or ``.start()``, then ``.stop()``).

    ``devices``: ``PROFILE@ADDRESS`` strings (or anything whose ``str`` is one); none
    and no scenario devices: one of each bundled profile (``scenario.DEFAULT_DEVICES``).
    ``faults``: fault specs (``faults.parse_fault``); ``sets``/``options``:
    ``PROFILE@ADDRESS.NAME=VALUE`` as on the command line; ``tcp``: True (a free port on
    127.0.0.1) or ``"HOST:PORT"``; ``tick``: seconds per value step (None: frozen);
    ``tap``: a link to a second pty that hears every byte on the line (``.tap_port``).
    """
    config = build([str(d) for d in devices], scenario=scenario, sets=sets, options=options,
                   faults=faults, seed=seed, baudrate=baudrate, turnaround=turnaround,
                   tick=tick, profile_dirs=profile_dirs)
    return SimulatedBus(config, tcp=tcp, link=link, on_wire=on_wire, tap=tap)


class SimulatedLines:
    """Several simulated lines (one pty or TCP port each), started and stopped together."""

    def __init__(self, lines: Sequence[SimulatedBus]) -> None:
        self.lines = list(lines)

    def start(self) -> SimulatedLines:
        try:
            for line in self.lines:
                line.start()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        for line in self.lines:
            line.stop()

    def __enter__(self) -> SimulatedLines:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def __iter__(self) -> Iterator[SimulatedBus]:
        return iter(self.lines)

    def __len__(self) -> int:
        return len(self.lines)

    def line_of(self, unit: int) -> SimulatedBus:
        """The line that serves the device configured at ``unit``."""
        for line in self.lines:
            if any(d.address == unit for d in line.config.devices):
                return line
        raise KeyError(unit)


def simulated_lines(devices: Sequence[str] = (), *, baudrate: int | None = None,
                    one_line: bool = False, faults: Sequence[str] = (),
                    scenario: str | Path | None = None, tcp: bool | str = False,
                    seed: int | None = None, sets: Sequence[str] = (),
                    options: Sequence[str] = (), turnaround: float | None = None,
                    tick: float | None = 1.0, profile_dirs: Iterable[Path] = (),
                    link: str | None = None,
                    on_wire: Callable[[WireFrame], None] | None = None,
                    tap: str | None = None, echo: bool = False) -> SimulatedLines:
    """The devices on lines that could exist (``scenario.split_lines``), one port each.

    Arguments as ``simulated_bus``. ``baudrate``: wire timing, and the speed preferred
    for the first line; ``one_line``: every device on one line (at ``baudrate``, or at
    any speed without it), as asked, even one that could not run there. ``link``: the
    first line's link; line N's gets N appended. ``tcp`` ``HOST:PORT``: line N listens
    on PORT + N - 1 (a free port each with PORT 0 or ``True``). ``tap``: as ``link``.
    """
    config = build([str(d) for d in devices], scenario=scenario, sets=sets, options=options,
                   faults=faults, seed=seed, baudrate=baudrate, turnaround=turnaround,
                   tick=tick, profile_dirs=profile_dirs)
    lines = (config,) if one_line or (config.baudrate and baudrate is None) \
        else split_lines(config, baudrate)
    out = []
    for i, line in enumerate(lines):
        where: bool | str = tcp
        if isinstance(tcp, str) and i:
            host, _, port = tcp.rpartition(":")
            where = f"{host}:{int(port) + i if int(port or 0) else 0}"
        out.append(SimulatedBus(line, tcp=where, link=f"{link}{i + 1}" if link and i else link,
                                on_wire=on_wire, tap=f"{tap}{i + 1}" if tap and i else tap))
        out[-1].echo = echo  # ``echo``: behind an adapter that echoes the master's requests
    return SimulatedLines(out)
