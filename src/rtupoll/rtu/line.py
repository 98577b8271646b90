"""The master's line discipline for one RS-485 line: sans-IO, in the spirit of h11.

Fed what was sent, what was received and the time (``now``, any monotonic clock, real
or virtual), it says when the next frame may go, which received bytes answer the
request in flight, and how an unanswered attempt is classified. It does no I/O and
reads no clock, so every rule is tested in virtual time; ``rtupoll.io.bus`` is the thin
adapter that feeds it from a port.

**Silence.** A frame may go 3.5 character times (``Framing.silence``) after the last
byte received and after the previous frame left the wire. After a timeout the line
must also have been quiet for the drain period (by default the timeout that expired),
but never longer than ``drain_limit`` drain periods: a line that never goes quiet
must not hold the master for ever.

**Idle gap.** Some devices hear a request only after a longer silence than 3.5
characters (the "T delay" of their manuals: Growatt asks for 850 ms between commands).
A request names the gap its unit needs (``Transaction(idle_gap=)``, which tells it to
``set_idle_gap``; ``idle_gap`` on the line: every unit's), and a request to that unit
may go only once the line has been silent that long: counted, as the silence is, from
the last byte on the line, whoever sent it (``ready_at(unit=)``). The line keeps the
gap last named for the unit: it is owed before every request to the device, also one
that names none (a gateway's pass-through, a write). A unit without one costs one
dictionary look-up.

**Learned idle gap.** A device that needs a gap nobody set looks slow: its first
attempt, sent right after another device's reply, is not heard; the retry, after a
whole timeout of silence, is answered. Taken for a late answer to the first attempt,
that would raise the learned timeout to its ceiling and starve the device. So when a
retry is answered after a silence ``_longer`` than that of every earlier attempt of
the same request, none of which heard anything at all, the answer is the retry's (its
reply time counted from the retry, never counted late: the timeout does not climb).
The first time, the earlier attempts stay outstanding as *suspects* (a one-off late
reply looks the same): an answer to one while no longer attempt is in flight means
the device heard it and is slow, not deaf: it is counted late as ever (the timeout
learns), and the unit learns no gap for ``GAP_REFUTED`` seconds. The second time (a
suspect among them, or a gap learned already) the unit's gap is raised: to twice the
silence that was not enough (at least ``GAP_STEP``), never beyond the silence that
worked nor ``GAP_MAX``; a silence of ``GAP_MAX`` that was not enough is no gap. A
learned gap halves every ``GAP_HALF_LIFE`` seconds (a device that needed a pause for
a while is not slowed for ever; one that still needs it raises it again) and is gone
below the silence (``learned_gap``; ``UnitCounts.gap`` for a unit's health).

**Which reply answers which request.** RTU has no transaction id: a read reply carries
only the unit, the function and a byte count, so a late reply to one request looks
exactly like the answer to the next request of the same shape. A timer alone cannot
settle that; the line keeps account instead. Every request sent to a unit joins that
unit's *outstanding* queue and leaves it only when a frame is identified as its answer
(or after ``horizon`` seconds). A frame from a unit answers one of the unit's
outstanding requests that it fits (devices and gateways do not always answer in
order). Hence:

- a frame is taken as the answer only when every outstanding request it fits is the
  request in flight or an identical one (same unit, function, addresses): a late
  answer to an earlier attempt of the same read is a right answer;
- a frame that fits a *different* outstanding request may be that request's late
  reply: it is counted as late (per unit) and never taken for the answer in flight;
  the attempt goes on waiting for its own answer;
- a frame that begins before the request in flight was sent cannot answer it (the
  request's own wire time is not counted: simulators and gateways answer sooner);
- frames of other units, noise and stray bytes are skipped; the answer is found
  wherever it starts in what arrived (resynchronisation).

So that the line never has to guess, a request is not sent while an earlier,
*different* request to the same unit and function may still be answered
(``hazard_until``): a request that timed out may be answered up to ``LATE_FACTOR``
timeouts late (counted in the request's ``patience``, ``expire``, when that is longer
than the timeout given: a timeout learned shorter than the manual's does not shorten
the window; or ``SETTLE_FACTOR`` times the longest reply time seen from that unit, if
longer; at most ``horizon``); a request whose answer was taken from an identical
earlier request's late reply may still be answered within ``SETTLE_FACTOR`` reply
times. Its answer arriving ends the wait at once. The bus waits for this outside
its lock, so other devices keep the line busy meanwhile. Should a frame still fit
an older different request (a device that dropped it and answers a later one), it
is counted late and the attempt times out: never a wrong value, at worst a retry.
What this cannot guarantee: a reply later than the late window of its request, a
device that answers one request twice, and frames from a second master.

**Echo.** A 2-wire adapter whose receiver is always on hands every request back
before the device's reply. With ``echo`` on, the line consumes that echo as part of
each attempt: the first bytes received after a request must be the request, byte for
byte; anything else ends the attempt as garbled (a collision on the wire, or an
adapter that does not echo). With ``echo`` off, a request coming back is detected on
the first request, whether its bytes come one by one as they leave the wire or all
at once (reads and FC15/16, whose echo is no reply; FC05/06, whose echo is byte for
byte the device's reply, once an echo has been seen on the line): never taken for the
answer, never counted late. Then either the attempt ends garbled with ``ECHO_HINT``
(``Garbled.final``: a retry would come back the same; a one-shot command says to add
--echo), or, with ``adopt_echo`` (``poll``), the echo is consumed and the line goes on
with ``echo`` on (``echo_found``; ``ECHO_FOUND`` says so): the device's reply that
follows is the first attempt's answer.

**Reply time.** For every frame it explains, the line records the device's reply
time: from the end of the request on the wire (its first byte's time plus its wire
time) to the reply's first byte, per unit (``reply_time``; ``late_reply_time`` for late
replies; ``Answer.reply_time``). It is the evidence ``rtupoll.jobs.timeouts`` learns
each device's timeout from. When several identical requests are outstanding it is
counted from the oldest: never shorter than the truth.

**Garbled replies** are known at once: a complete frame from the unit, with the
request's function, whose CRC is wrong ends the attempt (``Garbled``) without
waiting for the timeout. It *settles* the request: the device answered (the line
garbled it), so the request leaves the outstanding queue at once. The retry, sent
after the silence, is then the only one its answer fits: that answer is never
counted late, its reply time is the retry's own (so a noisy line never looks like a
slow device to the learned timeout), and a different request is not held for it.
An attempt that ends unanswered is classified by
``rtupoll.rtu.match.diagnose``: truncated, mismatched or garbled (``FrameError``) or
plain silence (``DeviceTimeout``).
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import field

from rtupoll.frozen import frozen, mutable
from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.functions import MAX_FRAME, echoed_by_design, reply_length
from rtupoll.rtu.match import Expect, answers, diagnose, expect_for
from rtupoll.rtu.timing import Framing

HORIZON = 60.0  # seconds after which no late reply is expected, whatever the evidence
LATE_FACTOR = 12  # a request that timed out may still be answered this many timeouts late
SETTLE_FACTOR = 3  # an answered-looking request may still be answered this many latencies late
DRAIN_LIMIT = 3  # at most this many drain periods after a timeout, even on a busy line
GAP_STEP = 0.01  # seconds: the least idle gap learned
GAP_MAX = 1.0  # seconds: the longest idle gap learned; beyond, a device is slow, not deaf
GAP_HALF_LIFE = 600.0  # seconds in which a learned idle gap halves
GAP_REFUTED = 600.0  # seconds a unit whose unheard attempt was answered after all learns none
ECHO_HINT = ("the adapter echoes every request back (a 2-wire adapter whose receiver is "
             "always on): add --echo (echo: true on the bus in a site file)")
ECHO_FOUND = ("the adapter echoes every request back (a 2-wire adapter whose receiver is "
              "always on): each echo is consumed from the first one on, as with --echo; say "
              "so with --echo (echo: true on the bus in a site file)")


@mutable(slots=True)  # made per attempt: plain, slots (CPU)
class Outstanding:
    """A request whose answer has not been identified yet."""

    request: bytes
    expect: Expect
    sent: float  # when its first byte went out
    expires: float  # after this no answer to it is expected any more
    idle: float = 0.0  # the silence on the line before it went
    retry: bool = False  # a retry of the same request within one transaction
    silent: bool = False  # its attempt ended with nothing received at all
    suspect: bool = False  # taken for not heard by the device (``Line._unheard``)


@frozen
class Answer:
    frame: bytes
    # seconds from the end of the (oldest matching) request on the wire to the reply's
    # first byte: the device's own time to answer, wire time excluded (never below 0)
    reply_time: float = field(default=0.0, compare=False)


@frozen
class Garbled:
    why: str
    final: bool = False  # no retry would fare better (an echo with echo off): give up


@mutable(slots=True)  # made per attempt: plain, slots (CPU)
class Attempt:
    """The request in flight (its outstanding entry) and what has arrived for it."""

    entry: Outstanding
    rx: bytearray = field(default_factory=bytearray)  # every byte received during it


@mutable
class LineCounts:
    """What the line saw, per unit where it is a unit's: every attempt is counted once,
    by how it ended (answered, ``garbled`` or ``timeouts``; an echo seen with echo off
    counts in ``echoes`` only)."""

    late: Counter[int] = field(default_factory=Counter)  # late replies, per unit
    unsolicited: int = 0  # frames and bursts that answered nothing we asked
    echoes: int = 0  # requests that came back with echo off (the adapter echoes)
    gap_raised: Counter[int] = field(default_factory=Counter)  # learned idle gap raises
    garbled: Counter[int] = field(default_factory=Counter)  # attempts ended by a garbled reply
    timeouts: Counter[int] = field(default_factory=Counter)  # attempts that got no reply
    retried: Counter[int] = field(default_factory=Counter)  # answered only by a retry


class UnitCounts:
    """One unit's share of what a line counts, read when asked (a device's health,
    ``jobs.stats``; late replies heard between its requests, ``jobs.timeouts``): nothing
    is copied per transaction. Every attempt ends answered, garbled or timed out (or
    as an echo, with echo off)."""

    __slots__ = ("line", "unit")

    def __init__(self, line: Line, unit: int) -> None:
        self.line, self.unit = line, unit

    @property
    def late(self) -> int:
        """Replies that came after their request had timed out (never decoded)."""
        return self.line.counts.late.get(self.unit, 0)

    @property
    def late_reply_time(self) -> float | None:
        """The reply time of the unit's last late reply, if it sent one."""
        return self.line.late_reply_time.get(self.unit)

    @property
    def timeouts(self) -> int:
        """Attempts that got no reply."""
        return self.line.counts.timeouts.get(self.unit, 0)

    @property
    def garbled(self) -> int:
        """Attempts ended by a garbled reply (an echo is not one)."""
        return self.line.counts.garbled.get(self.unit, 0)

    @property
    def retried(self) -> int:
        """Transactions answered only by a retry."""
        return self.line.counts.retried.get(self.unit, 0)

    @property
    def gap(self) -> float:
        """The idle gap a request to the unit waits for, beyond the 3.5 characters (0: none)."""
        return self.line.gaps.get(self.unit, self.line.line_gap)

    @property
    def gap_learned(self) -> bool:
        """Its gap is (also) learned (``Line.learned_gap``), not only set."""
        return self.unit in self.line.learned


class Line:
    """One line, one master. See the module docstring for the rules."""

    def __init__(self, framing: Framing, *, drain: float | None = None,
                 horizon: float = HORIZON, drain_limit: int = DRAIN_LIMIT,
                 echo: bool = False, idle_gap: float = 0.0) -> None:
        self.framing = framing
        self.echo = echo  # the adapter echoes each request: consume it
        # echo off and a request comes back: consume it and turn echo on (``poll``),
        # rather than end the transaction (a one-shot command says to add --echo)
        self.adopt_echo = False
        self.echo_found = False  # an echo came back with echo off (``adopt_echo``: adopted)
        self._echo = b""  # the echo still expected (echo on)
        self.counts = LineCounts()
        self._drain, self._horizon, self._drain_limit = drain, horizon, drain_limit
        self.last_rx = self.tx_end = self.timeout_at = float("-inf")
        self.drain_for = 0.0  # >0: the line must be quiet this long before the next request
        self.attempt: Attempt | None = None
        self._outstanding: dict[int, deque[Outstanding]] = {}
        self._latency: dict[int, float] = {}  # per unit: the longest reply time seen lately
        # per unit: the reply time (``Answer.reply_time``) of the last answer, and of the
        # last late reply (an answer to a request that had timed out or was superseded)
        self.reply_time: dict[int, float] = {}
        self.late_reply_time: dict[int, float] = {}
        self._buf = bytearray()  # received bytes not yet explained
        self._marks: list[tuple[int, float]] = []  # (offset in _buf, arrival time) per chunk
        self._idle_burst = False
        # who looks at the line's bytes (--traffic, --capture): (sent?, bytes), as they go
        # out and come in; None: nobody, and nothing is called
        self.tap: Callable[[bool, bytes], None] | None = None
        # the silence before a request: the line's (every unit's) and per unit, as set
        self.idle_gap = idle_gap
        self._gap_set: dict[int, float] = {}
        # the gap each unit gets (set, learned, the line's), where above the 3.5 characters
        self.gaps: dict[int, float] = {}
        self._quiet = max(framing.silence, idle_gap)  # any other unit's
        self.line_gap = idle_gap if idle_gap > framing.silence else 0.0  # theirs, beyond it
        # per unit, a learned idle gap: (seconds, since when); refuted: until when none is
        self.learned: dict[int, tuple[float, float]] = {}
        self._refuted: dict[int, float] = {}
        self._suspected: set[int] = set()  # units with suspects outstanding

    # -- when the next frame may go ------------------------------------------

    def set_idle_gap(self, unit: int, seconds: float) -> None:
        """The silence ``unit`` needs on the line before a request to it (0: none beyond
        the line's ``idle_gap`` and the 3.5 characters), as a request named it
        (``Transaction(idle_gap=)``), for every request to the unit from then on."""
        if self._gap_set.get(unit, 0.0) == seconds:
            return
        self._gap_set[unit] = seconds
        self._regap(unit)

    def gap(self, unit: int) -> float:
        """The silence a request to ``unit`` waits for (the 3.5 characters at least)."""
        return self.gaps.get(unit, self._quiet)

    @property
    def learned_gap(self) -> dict[int, float]:
        """Per unit, the idle gap learned (as of its last request), where one is."""
        return {unit: gap for unit, (gap, _) in self.learned.items()}

    def _regap(self, unit: int) -> None:
        learned = self.learned.get(unit)
        gap = max(self._gap_set.get(unit, 0.0), self.idle_gap, learned[0] if learned else 0.0)
        if gap > self.framing.silence:
            self.gaps[unit] = gap
        else:
            self.gaps.pop(unit, None)

    def ready_at(self, *, drain: bool = True, unit: int = -1) -> float:
        """The earliest time the next request (to ``unit``: its idle gap; none named: the
        line's) may start (``drain``: honour a drain)."""
        ready = max(self.last_rx, self.tx_end) + (
            self.gaps.get(unit, self._quiet) if self.gaps else self._quiet)
        if drain and self.drain_for:
            quiet = max(self.last_rx, self.timeout_at) + self.drain_for
            ready = max(ready, min(quiet, self.timeout_at + self._drain_limit * self.drain_for))
        return ready

    def opened(self, now: float) -> None:
        """A fresh port: count the silence from now."""
        self.last_rx = max(self.last_rx, now)

    # -- sending ---------------------------------------------------------------

    def send(self, request: bytes, now: float, retry: bool = False) -> None:
        """``request`` starts on the wire at ``now``; its answer is awaited (not a
        broadcast). ``retry``: a retry of the same request (``Transaction``)."""
        if self.tap is not None:
            self.tap(True, request)
        last = self.last_rx if self.last_rx > self.tx_end else self.tx_end
        idle = now - last  # the silence before it
        if self.learned and request[0] in self.learned:
            self._decay(request[0], now)
        self.tx_end = now + self.framing.wire_time(len(request))
        self.drain_for = 0.0
        if self._idle_burst:
            self.counts.unsolicited += 1
            self._idle_burst = False
        self._buf.clear()
        self._marks.clear()
        self._forget(now)
        self._echo = request if self.echo else b""
        exp = expect_for(request)
        if exp is None:  # a broadcast: nobody answers
            self.attempt = None
            return
        entry = Outstanding(request, exp, now, now + self._settle(exp.unit), idle, retry)
        self._outstanding.setdefault(exp.unit, deque()).append(entry)
        self.attempt = Attempt(entry)

    def after_broadcast(self, turnaround: float) -> None:
        """Give the devices time to act on a broadcast before the next request."""
        self.tx_end += turnaround

    # -- receiving ---------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> Answer | Garbled | None:
        """Bytes arrived at ``now``: the answer to the request in flight, a garbled
        reply that ends the attempt, or None (keep waiting)."""
        if not data:
            return None
        if self.tap is not None:
            self.tap(False, data)
        self.last_rx = now
        if self._echo:
            data, garbled = self._take_echo(data)
            if garbled:
                return garbled
            if not data:
                return None
        self._marks.append((len(self._buf), now))
        self._buf += data
        att = self.attempt
        if att is None:
            self._idle_burst = True
        else:
            att.rx += data
            request = att.entry.request
            if not self.echo and self._buf[:1] == request[:1]:
                if len(self._buf) < len(request) and request.startswith(self._buf):
                    return None  # the request coming back, perhaps: wait for the rest
                if self._buf.startswith(request) and self._is_echo(request):
                    self.counts.echoes += 1
                    self.echo_found = True
                    if not self.adopt_echo:
                        self.attempt = None
                        return Garbled(ECHO_HINT, final=True)
                    self.echo = True  # from now on each echo is consumed, as with --echo
                    self._consume(len(request))
                    del att.rx[:len(request)]
        while True:
            found = self._next_frame()
            if found is None:
                break
            start, frame = found
            began = max(t for off, t in self._marks if off <= start)
            self._consume(start + len(frame))
            if self._explain(frame, began) and att is not None:
                self.attempt = None
                if att.entry.retry:
                    self.counts.retried[frame[0]] += 1
                return Answer(frame, self.reply_time[frame[0]])
        if len(self._buf) > 2 * MAX_FRAME:
            self._consume(len(self._buf) - MAX_FRAME)
        if att is not None:
            why = self._garbled(att)
            if why:  # the request got its reply, garbled: it is settled, not outstanding
                self.attempt = None
                self._settle_garbled(att.entry)
                self.counts.garbled[att.entry.expect.unit] += 1
                return Garbled(why)
        return None

    def _settle_garbled(self, entry: Outstanding) -> None:
        """A garbled reply of the attempt's shape answered one of the unit's identical
        outstanding requests (the one that would have expired first, as in ``_explain``):
        it leaves the queue, so the retry's answer is the retry's (not late), its reply
        time is the retry's own, and a different request need not wait for it."""
        queue = self._outstanding.get(entry.expect.unit)
        if not queue:
            return
        same = [e for e in queue if e.request == entry.request]
        if same:
            queue.remove(min(same, key=lambda e: e.expires))
        if not queue:
            del self._outstanding[entry.expect.unit]

    def _take_echo(self, data: bytes) -> tuple[bytes, Garbled | None]:
        """Echo on: consume the expected echo from ``data``; what is left, or the attempt
        ending garbled when the echo differs from the request sent."""
        n = min(len(data), len(self._echo))
        if data[:n] == self._echo[:n]:
            self._echo = self._echo[n:]
            return data[n:], None
        sent, self._echo = self._echo, b""
        att, self.attempt = self.attempt, None
        if att is None:  # a broadcast's echo: nothing waits for it
            self.counts.unsolicited += 1
            return b"", None
        self.counts.garbled[att.entry.expect.unit] += 1
        return b"", Garbled(f"the adapter's echo differs from the request sent (expected "
                            f"{sent[:n].hex(' ')}, got {data[:n].hex(' ')}): a collision, or "
                            "an adapter that does not echo (then drop --echo)")

    def _is_echo(self, request: bytes) -> bool:
        """Echo off, ``request`` came back: an echo, unless it is byte for byte a normal
        reply (FC05/06, FC08's return query data) and no echo has been seen on this line
        yet."""
        return self.counts.echoes > 0 or not echoed_by_design(request)

    def _consume(self, n: int) -> None:
        """Drop the first ``n`` buffered bytes (explained, or too old to matter)."""
        if n >= len(self._buf):  # all of it: the usual case
            self._buf.clear()
            self._marks.clear()
            return
        del self._buf[:n]
        keep = [(off - n, t) for off, t in self._marks if off > n]
        older = [t for off, t in self._marks if off <= n]
        if self._buf and older and (not keep or keep[0][0] > 0):
            keep.insert(0, (0, older[-1]))
        self._marks = keep

    def _next_frame(self) -> tuple[int, bytes] | None:
        """The first CRC-valid reply frame in the buffer, wherever it starts."""
        buf = bytes(self._buf)
        for i in range(max(0, len(buf) - 3)):
            n = reply_length(buf[i : i + MAX_FRAME])
            if n is not None and i + n <= len(buf) and crc_ok(buf[i : i + n]):
                return i, buf[i : i + n]
        return None

    def _explain(self, frame: bytes, began: float) -> bool:
        """Account for one valid frame; True when it answers the attempt in flight.

        The frame answers one of the unit's outstanding requests it fits (sent before it
        began). Devices and gateways do not always answer in order, so which one is
        only certain when they are all the same request; the one that would have
        expired first is taken off (the others, and so the longest late window, stay)."""
        unit, att = frame[0], self.attempt
        fits = [e for e in self._outstanding.get(unit, ()) if e.sent <= began
                and answers(frame, e.expect)]
        if not fits:
            self.counts.unsolicited += 1
            return False
        in_flight = att.entry if att is not None else None
        queue = self._outstanding[unit]
        # (one fit and no suspects, the usual case: none of this applies)
        if len(fits) > 1 and in_flight in fits and self._unheard(unit, fits, in_flight, began):
            assert in_flight is not None
            for e in fits:  # answered; the attempts that were not heard: see _unheard
                if e is in_flight or (e.silent and not e.suspect):
                    queue.remove(e)
            if not queue:
                del self._outstanding[unit]
            self._latency[unit] = max(began - in_flight.sent,
                                      0.95 * self._latency.get(unit, 0.0))
            self.reply_time[unit] = max(
                0.0, began - in_flight.sent - self.framing.wire_time(len(in_flight.request)))
            return True
        if self._suspected and unit in self._suspected and any(e.suspect for e in fits):
            self._refute(unit, began)  # one taken for not heard may be answered: it was heard
        gone = min(fits, key=lambda e: e.expires)
        queue.remove(gone)
        if not queue:  # nothing unanswered: the next request's hazard check is quick
            del self._outstanding[unit]
        first = min(fits, key=lambda e: e.sent)
        oldest = first.sent
        self._latency[unit] = max(began - oldest, 0.95 * self._latency.get(unit, 0.0))
        took = self.reply_time[unit] = max(
            0.0, began - oldest - self.framing.wire_time(len(first.request)))
        taken = in_flight is not None and all(e.request == in_flight.request for e in fits)
        # late: another request's reply, or (in order) an earlier attempt's of this one
        if not taken or first is not in_flight:
            self.counts.late[unit] += 1
            self.late_reply_time[unit] = took
        return taken

    # -- the learned idle gap ---------------------------------------------------

    def _unheard(self, unit: int, fits: list[Outstanding], in_flight: Outstanding,
                 began: float) -> bool:
        """Whether one frame that fits ``fits`` (the attempt in flight among them) is the
        answer in flight's, the others not heard by the device (module docstring):

        - a retry answered after a longer silence than every earlier attempt of it, none
          of which heard anything: they were not heard. The first time (for the unit)
          they stay outstanding as *suspects*, so that an answer to one is still seen;
          the second time (a suspect among them, or a gap learned already) the unit's
          gap is raised and they are forgotten;
        - suspects, and an attempt in flight sent after a longer silence than any of
          them: its answer (the suspects stay).

        Anything else, a suspect among them, refutes (``_refute``)."""
        older = [e for e in fits if e is not in_flight]
        if any(e.request != in_flight.request or not _longer(in_flight.idle, e.idle)
               for e in older) or self._refuted.get(unit, -math.inf) > began:
            return False
        fresh = [e for e in older if not e.suspect]
        if not fresh:
            return True  # suspects only: the answer in flight's
        if not in_flight.retry or not all(e.silent for e in fresh):
            return False
        short = max(e.idle for e in fresh)
        if short >= GAP_MAX:  # that long a silence was not enough: no gap explains it
            return False
        if len(fresh) == len(older) and unit not in self.learned:  # the first time
            for e in fresh:
                e.suspect = True
            self._suspected.add(unit)
            return True
        was = self.learned.get(unit, (0.0, began))[0]
        gap = min(GAP_MAX, in_flight.idle, max(GAP_STEP, 2 * short))
        self.learned[unit] = (max(gap, was), began)
        self._regap(unit)
        self.counts.gap_raised[unit] += 1
        for e in older:
            e.suspect = False
        return True

    def _refute(self, unit: int, now: float) -> None:
        """An attempt taken for unheard may have been answered: ``unit`` is slow, not deaf.
        Its learned gap goes, and it learns none for ``GAP_REFUTED`` seconds."""
        self._refuted[unit] = now + GAP_REFUTED
        self._suspected.discard(unit)
        for e in self._outstanding.get(unit, ()):
            e.suspect = False
        if self.learned.pop(unit, None) is not None:
            self._regap(unit)

    def _decay(self, unit: int, now: float) -> None:
        """A learned gap halves every ``GAP_HALF_LIFE`` seconds; below the silence it is gone."""
        gap, since = self.learned[unit]
        left = gap * 0.5 ** ((now - since) / GAP_HALF_LIFE)
        if left <= self.framing.silence:
            del self.learned[unit]
        else:
            self.learned[unit] = (left, now)
        self._regap(unit)

    def _garbled(self, att: Attempt) -> str | None:
        """A complete frame from the unit with the request's function and a bad CRC."""
        exp, buf = att.entry.expect, bytes(self._buf)
        for head in (bytes((exp.unit, exp.function)), bytes((exp.unit, exp.function | 0x80))):
            i = buf.find(head)
            if i >= 0:
                n = reply_length(buf[i : i + MAX_FRAME])
                if n is not None and i + n <= len(buf):
                    return f"CRC error in reply: {buf[i : i + n][:24].hex(' ')}"
        return None

    # -- an attempt that got no answer -------------------------------------------

    def expire(self, now: float, timeout: float, patience: float = 0.0) -> str | None:
        """The attempt's deadline passed: None for a timeout (silence, noise, other
        units' frames), else why what arrived is a garbled reply. The request stays
        outstanding (its late window counted in ``patience`` when that is longer than
        ``timeout``: a learned timeout does not shorten it), and the next request waits
        for the drain (by default ``timeout``, the time the device was given)."""
        att, self.attempt = self.attempt, None
        self.timeout_at = now
        self.drain_for = self._drain if self._drain is not None else timeout
        if att is None:
            return None
        unit = att.entry.expect.unit
        att.entry.silent = not att.rx
        late = max(LATE_FACTOR * (timeout if timeout > patience else patience),
                   SETTLE_FACTOR * self._latency.get(unit, 0))
        att.entry.expires = att.entry.sent + min(self._horizon, late)
        why = diagnose(bytes(att.rx), att.entry.expect)
        (self.counts.garbled if why else self.counts.timeouts)[unit] += 1
        return why

    def hazard_until(self, request: bytes, now: float) -> float:
        """Until when ``request`` must not be sent: while an earlier, different request
        to the same unit may still be answered with a reply of the very shape of
        ``request``'s (a read reply names no address). 0 when it may go now. Identical
        requests are no hazard; exception replies, which name only the function, are
        never taken from an ambiguous frame (see ``_explain``)."""
        if request[0] not in self._outstanding:  # nothing unanswered: the usual case
            return 0.0
        self._forget(now)
        exp = expect_for(request)
        queue = self._outstanding.get(request[0], ())
        if exp is None or not queue:
            return 0.0
        return max((e.expires for e in queue if e.request != request
                    and e.expect.prefix == exp.prefix and e.expect.length == exp.length),
                   default=0.0)

    def _settle(self, unit: int) -> float:
        """How long an answered-looking request may still be answered: a few of the
        unit's reply times (at least a frame's wire time)."""
        return max(SETTLE_FACTOR * self._latency.get(unit, 0.0),
                   self.framing.wire_time(MAX_FRAME) + self.framing.silence)

    def _forget(self, now: float) -> None:
        """Drop the requests no answer is expected to any more: not the one in flight,
        which is expected until its attempt ends (``expire`` then sets its late window)."""
        if not self._outstanding:
            return
        flying = self.attempt.entry if self.attempt is not None else None
        for unit, queue in list(self._outstanding.items()):
            for e in [e for e in queue if e.expires < now and e is not flying]:
                queue.remove(e)
            if not queue:
                del self._outstanding[unit]


def _longer(idle: float, than: float) -> bool:
    """A silence that tells apart from ``than``: twice as long, and ``GAP_STEP`` longer."""
    return idle >= max(2 * than, than + GAP_STEP)
