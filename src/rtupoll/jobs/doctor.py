"""``rtupoll doctor``'s checks: the adapter and, given an address, one device, each a
finding with its fix.

What a technician otherwise learns from issue threads after "it does not answer": the
port's real open error, an adapter that echoes what it sends, a USB latency timer that
delays every reply, whether the kernel switches an RS-485 transceiver's direction, and
of a device its reply time, pauses inside its replies, and whether it needs a silence
before it hears a request. Every probe is a request through the line discipline; the
bytes that come back are watched through the line's tap, with the line's clock.
"""

from __future__ import annotations

import itertools
import math
import statistics
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from rtupoll.errors import BusError, DeviceTimeout
from rtupoll.io import clock
from rtupoll.io.latency import LATENCY_OK, latency_timer, latency_warning
from rtupoll.io.syncbus import SyncBus
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadRequest

ECHO_UNIT = 247  # the highest address a device may have: rarely given, so rarely there
PROBE_TIMEOUT = 0.3  # seconds an echo probe waits
ECHO_TRIES = 3  # echo probes, at most, before an echo is said to come back all at once
QUIET = 1.0  # seconds of silence before the first read of a device (any idle gap it needs)
READS = 5  # reads of the device for its reply time
GAPS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0)  # idle gaps tried, seconds
GAP_TRIES = 3  # trials of a gap whose silence came out too long, at most
Chunks = list[tuple[float, bytes]]  # (time, bytes) heard on the line, in order


@dataclass(frozen=True)
class Finding:
    check: str  # port, latency, rs485, echo, reply, pauses, idle-gap
    status: str  # ok, warning, problem, info
    text: str
    fix: str = ""
    value: float | None = None  # the measured figure, seconds (or None)

    def record(self) -> dict[str, object]:
        return {"check": self.check, "status": self.status, "finding": self.text,
                "fix": self.fix or None, "value": self.value}


class _Heard:
    """The line's tap: (time, sent?, bytes) of every chunk, on the line's clock."""

    def __init__(self) -> None:
        self.chunks: list[tuple[float, bool, bytes]] = []

    def __call__(self, sent: bool, data: bytes) -> None:
        self.chunks.append((clock.now(), sent, data))

    def since(self, mark: int) -> Chunks:
        return [(t, d) for t, _, d in self.chunks[mark:]]

    def silence_before(self, mark: int) -> float:
        """Seconds from the chunk before ``mark`` to the one at it (the request sent)."""
        if mark == 0 or mark >= len(self.chunks):
            return math.inf
        return self.chunks[mark][0] - self.chunks[mark - 1][0]


def _reply(chunks: Chunks, request: bytes) -> Chunks:
    """The chunks of the reply: after the request sent, and after its echo if the adapter
    sent it back (a chunk holding both is split, at its time)."""
    rest = chunks[1:]
    echo = b"".join(d for _, d in rest)[: len(request)] == request
    left = len(request) if echo else 0
    out = []
    for t, data in rest:
        if left >= len(data):
            left -= len(data)
            continue
        out.append((t, data[left:]))
        left = 0
    return out


class Doctor:
    """The checks on one open bus (a ``SyncBus``: nothing else runs on the line)."""

    def __init__(self, bus: SyncBus, *,
                 latency: Callable[[str], float | None] = latency_timer) -> None:
        """``latency``: how the adapter's latency timer is read (tests give a sysfs tree
        of their own)."""
        self.bus, self.latency = bus, latency
        self.heard = _Heard()
        shown = bus.line.tap  # --traffic's, if asked for: it still sees every byte

        def tap(sent: bool, data: bytes) -> None:
            self.heard(sent, data)
            if shown is not None:
                shown(sent, data)

        bus.line.tap = tap

    async def adapter(self) -> list[Finding]:
        """The port's own findings: latency timer, RS-485 mode, echo."""
        port = self.bus.settings.port
        out = []
        latency = self.latency(port)
        if latency is None:
            out.append(Finding("latency", "info", "no latency timer to read: not a USB "
                               "serial adapter whose driver exposes one (FTDI: sysfs on "
                               "Linux, the driver's registry on Windows), or a network port"))
        elif latency <= LATENCY_OK:
            out.append(Finding("latency", "ok", f"the USB adapter's latency timer is "
                               f"{latency * 1000:g} ms", value=latency))
        else:
            warning = latency_warning(port, latency) or ""
            said, _, fix = warning.partition("; ")
            out.append(Finding("latency", "warning", said.removeprefix(f"{port}: "), fix,
                               value=latency))
        out.append(_RS485[self.bus.rs485_mode()])
        out.append(await self._echo())
        return out

    async def _echo(self) -> Finding:
        """A request to an address no device should have: what comes back of it."""
        bus = self.bus
        request = ReadRequest(ECHO_UNIT, 3, 0, 1).frame()
        expected = bus.settings.echo
        for _ in range(ECHO_TRIES):
            _, chunks = await self._read(ECHO_UNIT, Table.HOLDING, 0, 1, PROBE_TIMEOUT)
            got = b"".join(d for _, d in chunks[1:])
            times = [t for t, _ in chunks[1:]]
            # an echo read late (a busy host, an adapter's latency timer) looks all at
            # once: only a pace seen says byte by byte, so an unpaced echo is probed again
            paced = len(times) > 1 and times[-1] - times[0] > \
                bus.framing.wire_time(len(request)) / 2
            if paced or not got.startswith(request):
                break
        if got.startswith(request):
            how = "byte by byte, as each leaves the wire" if paced else "all at once"
            if expected:
                return Finding("echo", "ok", f"the adapter echoes each request ({how}), and "
                               "--echo says so: the echo is taken off")
            bus.line.echo = True  # the device's checks below take the echo off
            return Finding("echo", "warning", f"the adapter echoes each request back ({how})"
                           ": a 2-wire adapter whose receiver stays on",
                           "add --echo (echo: true on the bus in a site file)")
        if not got:
            if expected:
                return Finding("echo", "problem", "--echo is given but the adapter echoes "
                               "nothing back", "leave --echo out")
            return Finding("echo", "ok", "no echo: the adapter does not hear its own "
                           "requests")
        return Finding("echo", "info", f"a request to unit {ECHO_UNIT} got "
                       f"{got[:16].hex(' ')}{' ...' if len(got) > 16 else ''} back: a device "
                       f"at {ECHO_UNIT}, another master, or noise on the line")

    async def device(self, unit: int, table: Table, address: int, count: int,
                     timeout: float) -> list[Finding]:
        """A device's reply time, the pauses inside its replies and its idle gap."""
        bus, char = self.bus, self.bus.framing.char_time

        async def read(after: float = 0.0) -> tuple[bool, Chunks]:
            time.sleep(after)  # (a SyncBus: nothing else runs meanwhile)
            return await self._read(unit, table, address, count, timeout)

        if not (await read(QUIET))[0]:
            return [Finding("reply", "problem", f"no reply from unit {unit} within "
                            f"{timeout * 1000:g} ms, after {QUIET:g} s of silence",
                            "check the address, the baud rate and parity ('rtupoll scan' "
                            "tries them), the A/B wires and the termination")]
        out: list[Finding] = []
        gap = 0.0
        if (await read())[0]:  # as soon as the line allows: 3.5 characters' silence
            out.append(Finding("idle-gap", "ok", "answers a request sent 3.5 characters "
                               "after the line went quiet: needs no idle gap", value=0.0))
        else:
            for g, longer in itertools.pairwise((*GAPS, math.inf)):
                if await self._answers_after(read, g, longer):
                    gap = g
                    break
            if gap:
                out.append(Finding("idle-gap", "warning", f"ignores a request sent sooner "
                                   f"than about {gap * 1000:g} ms after the last byte on the "
                                   "line", f"give it idle_gap: {gap:g} (--idle-gap {gap:g})",
                                   value=gap))
            else:
                return [*out, Finding("idle-gap", "problem", "answered once, then not again "
                                      f"up to {GAPS[-1]:g} s later", "check power and "
                                      "wiring: it answers only now and then")]
        times, pauses = [], []
        request = ReadRequest(unit, table.read_function, address, count).frame()
        for _ in range(READS):
            answered, rx = await read(gap * 1.5)
            reply = _reply(rx, request)
            if not answered or not reply:
                continue
            sent = rx[0][0]
            times.append(max(0.0, reply[0][0] - bus.framing.wire_time(len(reply[0][1]))
                             - sent - bus.framing.wire_time(len(request))))
            pauses.append(max((t1 - t0 - bus.framing.wire_time(len(d1))
                               for (t0, _), (t1, d1) in itertools.pairwise(reply)),
                              default=0.0))
        if times:
            median, worst = statistics.median(times), max(times)
            slow = worst >= 0.8 * timeout
            out.append(Finding("reply", "warning" if slow else "ok",
                               f"answers in {median * 1000:.1f} ms (median of {len(times)}), "
                               f"the longest {worst * 1000:.1f} ms; the timeout used is "
                               f"{timeout * 1000:g} ms",
                               f"give it a longer timeout (--timeout {2 * worst:.2f})"
                               if slow else "", value=median))
        longest = max(pauses, default=0.0)
        if longest > 1.5 * char:
            out.append(Finding("pauses", "warning", f"pauses up to {longest * 1000:.1f} ms "
                               "inside its replies: longer than 1.5 characters "
                               f"({1.5 * char * 1000:.2f} ms), which RTU counts as a frame's "
                               "end", "rtupoll joins such replies by their length and CRC, a "
                               "master that keeps the 1.5-character rule drops them: look at "
                               "the adapter's latency timer or the device's firmware",
                               value=longest))
        else:
            out.append(Finding("pauses", "ok", "no pause inside its replies longer than 1.5 "
                               "characters", value=longest))
        return out

    async def _answers_after(self, read: Callable[[float], Awaitable[tuple[bool, Chunks]]],
                             gap: float, longer: float) -> bool:
        """A read after a longer silence (it answers), then one after ``gap``: answered.
        A trial whose silence came out as long as the next gap tried (a busy host's
        sleep, a scheduler's delay) proves nothing of ``gap``: tried again, up to
        ``GAP_TRIES`` times."""
        for _ in range(GAP_TRIES):
            if not (await read(gap + 0.1))[0]:
                return False
            mark = len(self.heard.chunks)
            answered, _ = await read(gap)
            if not answered:
                return False
            if self.heard.silence_before(mark) < longer:
                return True
        return False

    async def _read(self, unit: int, table: Table, address: int, count: int,
                    timeout: float) -> tuple[bool, Chunks]:
        """One read, no retry: answered (an exception or garbled reply counts), and the
        chunks on the line meanwhile: the request (as it was sent), then what came."""
        mark = len(self.heard.chunks)
        try:
            await self.bus.read(unit, table, address, count, timeout=timeout, retries=0)
            answered = True
        except DeviceTimeout:
            answered = False
        except BusError:  # an exception reply or a garbled one: something answered
            answered = True
        return answered, self.heard.since(mark)


_RS485 = {
    "on": Finding("rs485", "ok", "the kernel's RS-485 mode is on: the driver switches the "
                  "transceiver's direction"),
    "off": Finding("rs485", "info", "the driver has the kernel's RS-485 mode, off now: a "
                   "transceiver on the UART's RTS needs it", "add --rs485 (rs485: true on "
                   "the bus)"),
    "none": Finding("rs485", "info", "no kernel RS-485 mode on this port"
                    + (" (Windows has none)" if sys.platform == "win32" else "")
                    + ": right for an adapter that switches direction by itself (most USB "
                    "ones); a bare UART transceiver needs --rs485 (RTS around each frame)"),
    "network": Finding("rs485", "info", "a network port: the gateway at the other end "
                       "drives the line"),
}
