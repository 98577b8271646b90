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
"""

from __future__ import annotations

import itertools
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from rtupoll.errors import UsageError
from rtupoll.rtu.functions import READS, Table, exception_response, read_response
from rtupoll.rtu.stream import Stream
from rtupoll.rtu.timing import Framing
from rtupoll.sim.engine import Engine, Transmission
from rtupoll.sniff.capfile import read_capture
from rtupoll.sniff.model import carried_words, parse_request

if TYPE_CHECKING:
    from rtupoll.sim.runner import SimulatedLines


@dataclass(frozen=True)
class Answer:
    """How one request was answered in the capture: bytes after a delay, or silence."""

    reply: bytes | None
    delay: float = 0.0  # from the end of the request to the start of the reply
    status: str = "ok"


class ReplayEngine(Engine):
    """An engine whose devices are the units of a capture."""

    def __init__(self, answers: dict[bytes, list[Answer]],
                 image: dict[int, dict[tuple[Table, int], int]], *,
                 silence: float = 0.0) -> None:
        super().__init__(())
        self.answers, self.image, self.silence = answers, image, silence
        self.served: Counter[bytes] = Counter()

    @property
    def units(self) -> list[int]:
        return sorted(self.image)

    def handle(self, frame: bytes, now: float = 0.0) -> list[Transmission]:
        self.requests += 1
        self.why_silent = ""
        unit = frame[0]
        captured = self.answers.get(frame)
        if captured:
            answer = captured[self.served[frame] % len(captured)]
            self.served[frame] += 1
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
            return exception_response(unit, fc, 1)
        start, count = int.from_bytes(frame[2:4], "big"), int.from_bytes(frame[4:6], "big")
        regs = self.image[unit]
        words = [regs.get((table, r)) for r in range(start, start + count)]
        if not words or any(w is None for w in words):
            return exception_response(unit, fc, 2)
        return read_response(unit, fc, [w for w in words if w is not None])


def load_replay(path: Path, *, framing: Framing | None = None, timed: bool = False
                ) -> tuple[ReplayEngine, Framing]:
    """A capture file -> the engine that replays it, and the capture's line settings.

    ``framing`` overrides (or, for a capture that does not record it, supplies) the
    line's settings; ``timed``: the server adds the 3.5-character silence itself.
    """
    capture = read_capture(path)
    line = framing or capture.framing
    if line is None:
        raise UsageError(f"{path} does not say its baud rate: give --baud")
    stream = Stream(line)
    answers: dict[bytes, list[Answer]] = {}
    image: dict[int, dict[tuple[Table, int], int]] = {}
    txs = list(itertools.chain.from_iterable(stream.feed(d, t) for t, d in capture.chunks))
    for tx in txs + stream.close():
        if tx.request is None or tx.status == "broadcast":
            continue
        req = tx.request.data
        unit = req[0]
        regs = image.setdefault(unit, {})
        reply = tx.reply.data if tx.reply is not None else None
        answers.setdefault(req, []).append(Answer(reply, tx.reply_time or 0.0, tx.status))
        r = parse_request(req)
        words = carried_words(tx, r)
        if words is not None and (table := r.table) is not None:
            regs.update(((table, r.start + i), w) for i, w in enumerate(words))
    if not answers:
        raise UsageError(f"{path}: no request in this capture to replay")
    return ReplayEngine(answers, image, silence=line.silence if timed else 0.0), line


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
        requests = [r for r in engine.answers if r[0] == unit]
        replies = sum(1 for r in requests for a in engine.answers[r] if a.reply is not None)
        out.append(f"  unit {unit}: {len(requests)} distinct request(s), {replies} captured "
                   f"repl{'y' if replies == 1 else 'ies'}, {len(engine.image[unit])} register(s)")
    out.append("Each captured request is answered as it was on site, in order; press Ctrl-C "
               "to stop.")
    return out
