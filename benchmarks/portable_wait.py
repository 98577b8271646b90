"""The portable wait's CPU per transaction at 115200 baud, against the descriptor's.

``rtupoll.io.waits`` waits on a port in one of two ways: ``FdWait`` (``select`` and one
``os.read`` on a tty's descriptor, POSIX) or ``PortWait`` (pyserial's ``read`` with the
port's timeout and ``in_waiting``: what a Windows COM port, ``rfc2217://`` and
``socket://`` get). Both drive the same ``SyncBus`` (``rtupoll read``, ``write``,
``guess``) on the same line: ``rtupoll simulate --baud 115200 --turnaround 0`` in its own
process (so the benchmark's CPU is the driver's alone), one Huiwen module read over and
over (co2, FC04 x1). The portable wait is given the same pty through pyserial with no
descriptor offered (``device_fd`` None: exactly what ``wait_on`` sees of a COM port), so
the two differ only in how they wait. The async ``Bus`` (``poll``, ``scan``, the
gateway) likewise: on the descriptor, and on a ``waits.Pump`` (what a port with no
descriptor gets: Windows's COM ports, ``rfc2217://``). For scale, pymodbus's own answer
to a port with no descriptor, its polling transport (``SerialTransport.force_poll``,
which pymodbus turns on by itself on Windows and rtupoll turns off), is measured the
same way against the same ``Bus`` on the descriptor.

Rounds alternate (descriptor, portable, ...), each ``--transactions`` long; CPU is this
process's ``time.process_time`` (all its threads), the rate transactions per second of
wall time. Printed: per-transaction CPU of each, the ratio portable / descriptor (the
goal: at most 1.5) and the rates (the goal: the same).

Run: .venv/bin/python benchmarks/portable_wait.py [--transactions 500] [--rounds 3]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rtupoll.io import own_port, waits
from rtupoll.io.port_settings import PortSettings
from rtupoll.io.syncbus import SyncBus, run
from rtupoll.rtu import Table

BAUD = 115200
UNIT, ADDRESS = 3, 30008  # the Huiwen's co2 (input 30009)


class NoDescriptor(own_port.Serial):
    """The pty as a COM port looks to ``wait_on``: no descriptor offered."""

    @property
    def device_fd(self) -> int | None:
        return None


def sync_round(path: str, n: int, portable: bool) -> tuple[float, float]:
    """(CPU s, wall s) of ``n`` reads through ``SyncBus``."""
    settings = PortSettings(path, baudrate=BAUD)
    opened: Any = None
    if portable:
        opened = NoDescriptor(path, baudrate=BAUD, timeout=waits.SLICE, exclusive=True)
    bus = SyncBus(settings, opened=opened)
    with bus:
        assert isinstance(bus._take, waits.PortWait if portable else waits.FdWait)
        run(bus.read(UNIT, Table.INPUT, ADDRESS, 1, timeout=0.5))  # warm
        cpu, wall = time.process_time(), time.perf_counter()
        for _ in range(n):
            run(bus.read(UNIT, Table.INPUT, ADDRESS, 1, timeout=0.5))
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    if opened is not None:
        opened.close()
    return cpu, wall


def async_round(path: str, n: int, poll: bool = False, pump: bool = False
                ) -> tuple[float, float]:
    """(CPU s, wall s) of ``n`` reads through the async ``Bus``; ``poll``: pymodbus's
    polling transport (what it does on Windows) instead of the event loop's reader;
    ``pump``: the loop's reader on a ``waits.Pump`` (what ``rfc2217://`` gets on POSIX),
    the pty offering no descriptor of its own."""
    from pymodbus.transport.serialtransport import SerialTransport

    from rtupoll.io.bus import Bus

    if pump:
        own = own_port.OwnPort
        saved = own.device_fd, own.fileno
        own.device_fd = property(lambda self: None)  # type: ignore[assignment,method-assign]
        own.fileno = _pumped  # type: ignore[method-assign]
        try:
            return async_round(path, n)
        finally:
            own.device_fd, own.fileno = saved  # type: ignore[method-assign]

    async def main() -> tuple[float, float]:
        async with Bus(PortSettings(path, baudrate=BAUD)) as bus:
            await bus.read(UNIT, Table.INPUT, ADDRESS, 1, timeout=0.5)
            cpu, wall = time.process_time(), time.perf_counter()
            for _ in range(n):
                await bus.read(UNIT, Table.INPUT, ADDRESS, 1, timeout=0.5)
            return time.process_time() - cpu, time.perf_counter() - wall

    was = SerialTransport.force_poll
    SerialTransport.force_poll = poll
    try:
        return asyncio.run(main())
    finally:
        SerialTransport.force_poll = was


def _pumped(self: Any) -> int:
    """``OwnPort.fileno`` of a port that offers no descriptor (``rfc2217://``'s path)."""
    if self._pump is None:
        self.timeout = waits.SLICE
        self._pump = waits.Pump(waits.PortWait(own_port._Base(self)))
    return int(self._pump.fileno())


def compare(name: str, one: Callable[[bool], tuple[float, float]], rounds: int, n: int,
            labels: tuple[str, str]) -> None:
    got: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    for _ in range(rounds):
        for other in (False, True):
            got[other].append(one(other))
    cpu = {k: statistics.median(c for c, _ in v) / n for k, v in got.items()}
    rate = {k: statistics.median(n / w for _, w in v) for k, v in got.items()}
    ratios = [p[0] / d[0] for d, p in zip(got[False], got[True], strict=True)]
    print(f"{name}:")
    for k, label in zip((False, True), labels, strict=True):
        print(f"  {label:<34} {cpu[k] * 1e6:7.0f} µs CPU/tx  {rate[k]:6.0f} tx/s")
    print(f"  CPU ratio {cpu[True] / cpu[False]:.2f} (rounds {min(ratios):.2f}-"
          f"{max(ratios):.2f}), rate ratio {rate[True] / rate[False]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transactions", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "bus"
        sim = subprocess.Popen([sys.executable, "-m", "rtupoll", "simulate", "--baud",
                                str(BAUD), "--turnaround", "0", "--tick", "0", "--link",
                                str(link), f"huiwen-aq@{UNIT}"], stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True)
        try:
            assert sim.stdout is not None
            while not link.exists():
                if sim.poll() is not None or not sim.stdout.readline():
                    raise SystemExit("the simulator did not start")
            path, n = str(link), args.transactions
            print(f"{n} reads a round, {args.rounds} rounds each, at {BAUD} baud "
                  f"(Python {sys.version.split()[0]})")
            compare("SyncBus (read, write, guess)", lambda p: sync_round(path, n, p),
                    args.rounds, n, ("descriptor (FdWait)", "portable (PortWait)"))
            compare("Bus (poll, scan, the gateway)", lambda p: async_round(path, n, pump=p),
                    args.rounds, n, ("descriptor (the loop's reader)",
                                     "portable (a waits.Pump's reader)"))
            compare("Bus, pymodbus's answer to no descriptor",
                    lambda p: async_round(path, n, poll=p), args.rounds, n,
                    ("descriptor (the loop's reader)", "pymodbus's polling (force_poll)"))
        finally:
            sim.terminate()
            sim.wait()


if __name__ == "__main__":
    main()
