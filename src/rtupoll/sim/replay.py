"""Replaying a capture: the devices of a sniffed bus, answering as they did.

``rtupoll simulate --replay FILE`` serves what a capture (``rtupoll sniff --capture``)
recorded, so a field problem can be reproduced at the desk, in a test, or from a bug
report. The capture is split and paired by the sniffer's own core (``rtu.stream``);
then every request seen is answered the way it was answered on site, in order and
cycling: the same reply bytes (so the same register values), after the same reply
time; an exception again; silence where the device did not answer; the same garbled
bytes where its reply was garbled. A request the capture does not hold, to a unit it
does, is answered from the registers that unit's replies carried (latest values), or
with exception 02 where the capture knows nothing; other units stay silent.

The capture is streamed, never loaded whole: one pass at start learns its requests and
registers (memory: one entry per distinct request and register), then the answers are
read from the file as the requests come, one cursor for all, back to the start at its
end. A request asked less often than the capture holds it keeps at most ``AHEAD``
answers read ahead; older ones are skipped. So a capture of hours replays in the memory
of one of minutes.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from rtupoll.errors import UsageError
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.functions import READS, Table
from rtupoll.rtu.messages import ExceptionReply, ReadReply, TableRequest
from rtupoll.rtu.stream import Stream, Transaction
from rtupoll.rtu.timing import Framing
from rtupoll.sim.engine import Engine, Transmission
from rtupoll.sniff.capfile import CaptureStream
from rtupoll.sniff.model import carried_words

if TYPE_CHECKING:
    from rtupoll.sim.runner import SimulatedLines


@dataclass(frozen=True)
class Answer:
    """How one request was answered in the capture: bytes after a delay, or silence."""

    reply: bytes | None
    delay: float = 0.0  # from the end of the request to the start of the reply
    status: str = "ok"


AHEAD = 64  # answers kept per request read ahead of it (the cursor is shared)


@dataclass
class Captured:
    """What the capture holds for one distinct request: how often it was asked and
    answered (the banner's counts); the answers read ahead and not yet served."""

    asked: int = 0
    replies: int = 0
    ahead: deque[Answer] | None = None


def _answers(capture: CaptureStream, line: Framing) -> Iterator[tuple[bytes, Answer]]:
    """The capture's requests with how each was answered, in order, read from the file."""
    stream = Stream(line)

    def pairs(txs: list[Transaction]) -> Iterator[tuple[bytes, Answer]]:
        for tx in txs:
            if tx.request is not None and tx.status != "broadcast":
                reply = tx.reply.data if tx.reply is not None else None
                yield tx.request.data, Answer(reply, tx.reply_time or 0.0, tx.status)

    for t, data in capture.chunks():
        yield from pairs(stream.feed(data, t))
    yield from pairs(stream.close())


class ReplayEngine(Engine):
    """An engine whose devices are the units of a capture, read as it is served."""

    def __init__(self, capture: CaptureStream, line: Framing,
                 captured: dict[bytes, Captured],
                 image: dict[int, dict[tuple[Table, int], int]], *,
                 silence: float = 0.0) -> None:
        super().__init__(())
        self.capture, self.line, self.captured = capture, line, captured
        self.image, self.silence = image, silence
        self._cursor: Iterator[tuple[bytes, Answer]] = iter(())

    @property
    def units(self) -> list[int]:
        return sorted(self.image)

    def _next_answer(self, frame: bytes, c: Captured) -> Answer:
        """The next captured answer to ``frame``: read ahead from the shared cursor (and
        round from the start) until one comes; the others wait in their requests' queues."""
        if c.ahead:
            return c.ahead.popleft()
        for _ in range(2):  # the rest of this pass, then one whole pass: it is there
            for request, answer in self._cursor:
                if request == frame:
                    return answer
                other = self.captured.get(request)
                if other is not None:
                    if other.ahead is None:
                        other.ahead = deque(maxlen=AHEAD)
                    other.ahead.append(answer)
            self._cursor = _answers(self.capture, self.line)
        raise RuntimeError(f"the capture changed while replayed: {frame.hex(' ')} is gone")

    def handle(self, frame: bytes, now: float = 0.0, idle: float = math.inf,
               parity: str | None = None) -> list[Transmission]:
        """What the capture answered ``frame`` (``idle``, ``parity``: as ``Engine.handle``'s,
        unused: the capture's devices answered what they heard)."""
        self.requests += 1
        self.why_silent = ""
        unit = frame[0]
        captured = self.captured.get(frame)
        if captured:
            answer = self._next_answer(frame, captured)
            if answer.reply is None:
                self.why_silent = f"unit {unit} did not answer this request in the capture"
                return []
            self.replies += 1
            # the server adds the line's silence with wire timing; the rest is turnaround
            turnaround = max(0.0, answer.delay - self.silence)
            return [Transmission(answer.reply, unit, turnaround, explicit=True,
                                 notes=(f"replayed ({answer.status})",))]
        if unit not in self.image:
            self.why_silent = f"no unit {unit} in the capture"
            return []
        self.replies += 1
        return [Transmission(self._from_image(frame), unit, 0.0, explicit=True,
                             notes=("from the captured registers",))]

    def _from_image(self, frame: bytes) -> bytes:
        unit, fc = frame[0], frame[1]
        table = READS.get(fc)
        if table is None or not table.is_register or len(frame) != 8:  # registers only
            return ExceptionReply(unit, fc, ExceptionCode.ILLEGAL_FUNCTION).frame()
        start, count = int.from_bytes(frame[2:4], "big"), int.from_bytes(frame[4:6], "big")
        regs = self.image[unit]
        words = [regs.get((table, r)) for r in range(start, start + count)]
        if not words or any(w is None for w in words):
            return ExceptionReply(unit, fc, ExceptionCode.ILLEGAL_ADDRESS).frame()
        return ReadReply(unit, fc, tuple([w for w in words if w is not None])).frame()


def load_replay(path: Path, *, framing: Framing | None = None, timed: bool = False
                ) -> tuple[ReplayEngine, Framing]:
    """A capture file -> the engine that replays it, and the capture's line settings.

    ``framing`` overrides (or, for a capture that does not record it, supplies) the
    line's settings; ``timed``: the server adds the 3.5-character silence itself.
    """
    capture = CaptureStream(path)
    line = framing or capture.framing
    if line is None:
        raise UsageError(f"{path} does not say its baud rate: give --baud")
    stream = Stream(line)
    captured: dict[bytes, Captured] = {}
    image: dict[int, dict[tuple[Table, int], int]] = {}

    def learn(txs: list[Transaction]) -> None:
        for tx in txs:
            if tx.request is None or tx.status == "broadcast":
                continue
            req = tx.request.data
            regs = image.setdefault(req[0], {})
            c = captured.setdefault(req, Captured())
            c.asked += 1
            c.replies += tx.reply is not None
            r = tx.asked
            words = carried_words(tx, r)
            if words is not None and isinstance(r, TableRequest):
                regs.update(((r.table, r.address + i), w) for i, w in enumerate(words))

    for t, data in capture.chunks():  # one pass: the requests and the latest registers
        learn(stream.feed(data, t))
    learn(stream.close())
    if not captured:
        raise UsageError(f"{path}: no request in this capture to replay")
    return ReplayEngine(capture, line, captured, image,
                        silence=line.silence if timed else 0.0), line


def replay_lines(path: Path, *, baud: int | None = None, tcp: bool | str = False,
                 link: str | None = None, tap: str | None = None) -> SimulatedLines:
    """The capture's bus, ready to start: one line with real wire timing at the capture's
    speed (``baud`` for a capture that does not record it, or to override it), so each
    reply starts its captured reply time after the end of its request.
    """
    from rtupoll.sim.runner import SimulatedBus, SimulatedLines
    from rtupoll.sim.scenario import Scenario

    engine, line = load_replay(path, framing=Framing(baud) if baud else None, timed=True)
    config = Scenario((), baudrate=line.baudrate, tick=None)
    bus = SimulatedBus(config, tcp=tcp, link=link, tap=tap, engine=engine)
    return SimulatedLines([bus])


def banner(lines: SimulatedLines, path: Path) -> list[str]:
    """What ``simulate --replay`` prints: where, which units, and what to try."""
    bus = lines.lines[0]
    engine = bus.engine
    assert isinstance(engine, ReplayEngine)
    speed = bus.config.line_speed
    out = [f"Replaying {path} on {bus.port}" + (f", linked as {bus.link}" if bus.link else "")
           + (" (RTU over TCP" if bus.port.startswith("tcp:") else " (open it")
           + (f" at {speed} baud, with its wire timing)" if speed else ")")]
    if bus.tap_port:
        out.append(f"Tap (every byte on the line): {bus.tap_port}, linked as {bus.tap}")
    for unit in engine.units:
        requests = [r for r in engine.captured if r[0] == unit]
        replies = sum(engine.captured[r].replies for r in requests)
        out.append(f"  unit {unit}: {len(requests)} distinct request(s), {replies} captured "
                   f"repl{'y' if replies == 1 else 'ies'}, {len(engine.image[unit])} register(s)")
    out.append("Each captured request is answered as it was on site, in order; press Ctrl-C "
               "to stop.")
    return out
