"""A listen-only tap's byte stream -> frames -> transactions, sans-IO and in virtual time.

A sniffer sees both directions of an RS-485 pair as one byte stream, delivered in
chunks whose timing depends on the adapter. ``Stream`` is fed ``(bytes, arrival time)``
and gives back ``Transaction`` events; it never reads a clock (``tick(now)`` tells it
time has passed) and never does I/O, so every rule is tested with bytes and numbers.

Splitting. A frame ends where its structure says (the function table's lengths,
``rtu.functions``) *and* its CRC checks, not merely where the line went quiet: a slow
USB adapter can deliver half a frame, pause for a latency-timer tick and deliver the
rest, and that pause must not cut the frame in two; two frames glued without the
3.5-character silence (a fast device, a coarse adapter) must still come apart. The
silence is used where the bytes alone cannot decide: a head that forms no CRC-valid
frame is broken, and ends at the first silence after it, or where a valid frame
starts (stray bytes before a reply), whichever comes first. Bytes that stay
incomplete for ``hold`` seconds are reported as what they are (truncated frame, CRC
error, line noise).

Pairing. A request is answered by the next frame that ``rtu.match`` accepts for it
(same unit, same function or its exception, the expected length or echo); a reply
that arrives after another request went out, or after ``timeout``, is never taken
as the answer to anything else. A broken frame that starts like the awaited reply is
that reply, garbled: the transaction fails, it never yields a value.

Messages: a ``Transaction`` is bytes with their times; its request and reply as
messages (``asked``, ``answer``) are the strict parsers' (``rtu.messages``), parsed
when asked for.

Times: every byte's arrival is estimated from its chunk's arrival (the chunk's last
byte) and the character time, so a frame has a start and an end on the wire, and a
reply time is from the end of the request to the start of the reply (the device's
silence and turnaround), whatever the frames' lengths.
"""

from __future__ import annotations

from dataclasses import dataclass

from rtupoll.rtu import messages
from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.exception_codes import exception_name
from rtupoll.rtu.frames import NOT_A_FRAME, Direction, frame_at, lengths
from rtupoll.rtu.functions import (
    EXCEPTION_LENGTH,
    FUNCTIONS,
    MAX_FRAME,
    READ_FUNCTIONS,
    answer_length,
    reply_length,
    request_length,
)
from rtupoll.rtu.match import Expect, diagnose, expect_for
from rtupoll.rtu.timing import Framing

HOLD = 0.1  # seconds an incomplete frame waits for its rest before it is called broken
TIMEOUT = 1.0  # seconds after which an unanswered request counts as timed out

# a request seen on the line: its message, or why the strict parser refused it
Seen = messages.Request | messages.Malformed


@dataclass(frozen=True)
class WireFrame:
    """Bytes that belong together on the wire, with when they started and ended."""

    data: bytes
    start: float  # when its first byte began
    end: float  # when its last byte was complete

    @property
    def crc_ok(self) -> bool:
        return crc_ok(self.data)


@dataclass(frozen=True)
class Transaction:
    """One thing that happened on the line.

    ``status``: ``ok`` (a request and its reply), ``exception`` (answered with a Modbus
    exception), ``timeout`` (no reply within the timeout, or another request came
    first), ``garbled`` (the awaited reply arrived broken: CRC error, truncated,
    mismatched), ``broadcast`` (unit 0: nobody answers), ``orphan`` (a valid reply
    whose request was not seen, e.g. a late reply), ``noise`` (stray bytes between
    frames), ``broken`` (bytes with a bad CRC that answer no request seen). The
    bytes of ``noise`` and ``broken`` are in ``junk``.
    """

    status: str
    time: float  # the request's start, or the event's
    request: WireFrame | None = None
    reply: WireFrame | None = None
    note: str = ""
    junk: WireFrame | None = None

    @property
    def unit(self) -> int | None:
        frame = self.request or self.reply
        return frame.data[0] if frame is not None else None

    @property
    def function(self) -> int | None:
        frame = self.request or self.reply
        return frame.data[1] & 0x7F if frame is not None else None

    @property
    def reply_time(self) -> float | None:
        """From the end of the request to the start of the reply (silence + turnaround)."""
        if self.request is None or self.reply is None:
            return None
        return max(0.0, self.reply.start - self.request.end)

    @property
    def exception(self) -> int | None:
        r = self.reply
        return r.data[2] if self.status == "exception" and r is not None else None

    @property
    def asked(self) -> Seen | None:
        """The request's message (``rtu.messages.parse_request``; the stream checked its
        CRC), or the parser's ``Malformed``: a refused request addresses no table, so no
        register is ever attributed to it. None without a request. (Parsed at each call:
        take it once.)"""
        r = self.request
        if r is None:
            return None
        try:
            return messages.parse_request(r.data[1:-2], unit=r.data[0])
        except messages.Malformed as bad:
            return bad

    def answer(self, asked: Seen | None) -> messages.Reply | None:
        """The reply's message (``rtu.messages.parse_reply``) when the transaction is
        ``ok`` and the strict parser takes the reply as the answer to ``asked`` (this
        transaction's ``asked``)."""
        r = self.reply
        if self.status != "ok" or r is None or asked is None or \
                isinstance(asked, messages.Malformed):
            return None
        try:
            return messages.parse_reply(asked, r.data[1:-2], unit=r.data[0])
        except messages.Malformed:
            return None


class Stream:
    """Feed it chunks as they arrive; it returns the transactions they complete."""

    def __init__(self, framing: Framing, *, timeout: float = TIMEOUT, hold: float = HOLD
                 ) -> None:
        self.timeout = timeout
        self.hold = max(hold, 2 * framing.silence)
        self.char = framing.char_time
        self.gap = framing.silence * 0.9  # a little slack for the time estimates
        self.buf = bytearray()
        self.times: list[float] = []  # when each buffered byte was complete
        self.last = float("-inf")  # when the last byte seen was complete
        self.pending: WireFrame | None = None  # a request awaiting its reply
        self.expect: Expect | None = None

    # -- input ----------------------------------------------------------------
    def feed(self, data: bytes, t: float) -> list[Transaction]:
        """``data`` arrived, its last byte complete at ``t``."""
        if not data:
            return self.tick(t)
        n = len(data)
        first = max(t - (n - 1) * self.char, self.last)
        out = self.tick(first - self.char)
        step = (t - first) / (n - 1) if n > 1 else 0.0
        self.times.extend(first + i * step for i in range(n))
        self.buf += data
        self.last = t
        out += self._split(final=False)
        return out

    def tick(self, now: float) -> list[Transaction]:
        """Time passed without bytes until ``now``: incomplete frames and requests expire."""
        out: list[Transaction] = []
        if self.buf and now - self.last >= self.hold:
            out += self._split(final=True)
        if self.pending is not None and now - self.pending.end >= self.timeout:
            out.append(self._unanswered(f"no reply within {self.timeout:g} s"))
        return out

    def close(self) -> list[Transaction]:
        """The end of the capture: whatever is left is reported as it stands."""
        out = self._split(final=True) if self.buf else []
        if self.pending is not None:
            out.append(self._unanswered("no reply before the capture ended"))
        return out

    # -- splitting --------------------------------------------------------------
    def _answering(self) -> bytes | None:
        return self.pending.data if self.expect is not None and self.pending else None

    def _lengths(self, at: int) -> tuple[int, ...]:
        """Frame lengths (function table) that may start at ``buf[at]``, likeliest first."""
        return lengths(bytes(self.buf[at : at + 11]), Direction.EITHER, self._answering())

    def _valid_at(self, at: int, *, wait: bool = False) -> int | None:
        """Length of a complete, CRC-valid frame starting at ``buf[at]``, else None.
        ``wait``: None while a likelier length is still arriving (a request whose first
        bytes happen to make a CRC-valid reply must not be cut there)."""
        n = frame_at(self.buf, at, direction=Direction.EITHER, answering=self._answering(),
                     final=not wait)
        if n > 0:
            return n
        if n == NOT_A_FRAME and at == 0 and self._free_length():
            # the standard leaves its length to the data
            return next((n for n in range(5, min(len(self.buf), MAX_FRAME) + 1)
                         if crc_ok(bytes(self.buf[:n]))), None)
        return None

    def _free_length(self) -> bool:
        """The head is the awaited reply of a function whose replies have no set length."""
        exp = self.expect
        return exp is not None and len(self.buf) >= 2 and self.buf[0] == exp.unit \
            and self.buf[1] == exp.function and not FUNCTIONS[exp.function].reply.known

    def _gap_before(self, i: int) -> bool:
        return self.times[i] - self.char - self.times[i - 1] >= self.gap

    def _split(self, *, final: bool) -> list[Transaction]:
        out: list[Transaction] = []
        while self.buf:
            n = self._valid_at(0, wait=not final)
            if n is not None:
                out += self._frame(self._cut(n))
                continue
            size = len(self.buf)
            need = max(self._lengths(0), default=0)
            if not final and size < need:
                break  # the rest may come after a pause: a gap does not end a frame
            gap = next((i for i in range(1, size) if self._gap_before(i)), None)
            limit = gap if gap is not None else size - 3
            valid = next((i for i in range(1, limit) if self._valid_at(i) is not None), None)
            cut = valid if valid is not None else gap
            if cut is None:
                if not final and size <= MAX_FRAME:
                    break  # a frame glued to it is not complete yet
                cut = need if need and not final else size
            out += self._broken(self._cut(cut))
        return out

    def _cut(self, n: int) -> WireFrame:
        data, times = bytes(self.buf[:n]), self.times[:n]
        del self.buf[:n]
        del self.times[:n]
        return WireFrame(data, times[0] - self.char, times[-1])

    # -- pairing ----------------------------------------------------------------
    def _frame(self, frame: WireFrame) -> list[Transaction]:
        """A CRC-valid frame: the awaited reply, a new request, or a reply nobody asked for."""
        data, out = frame.data, []
        exp, req = self.expect, self.pending
        if exp is not None and req is not None and data[0] == exp.unit:
            if data[1] == exp.function | 0x80 and len(data) == EXCEPTION_LENGTH:
                self._clear()
                return [Transaction("exception", req.start, req, frame,
                                    f"exception {data[2]:02d} {exception_name(data[2])}")]
            free = not FUNCTIONS[exp.function].reply.known
            if data[1] == exp.function and (free or (len(data) == exp.size(data)
                                                     and data.startswith(exp.prefix))):
                self._clear()
                return [Transaction("ok", req.start, req, frame)]
            if data[1] & 0x7F == exp.function and not _is_request(data):
                self._clear()
                why = diagnose(data, exp) or "reply does not match the request"
                return [Transaction("garbled", req.start, req, frame, why)]
        if _is_request(data):
            if req is not None:
                out.append(self._unanswered("the next request came first"))
            if data[0] == 0:
                out.append(Transaction("broadcast", frame.start, frame))
            else:
                self.pending, self.expect = frame, _expect(data)
            return out
        what = f"unit {data[0]}" + (f" (exception {data[2]:02d})" if data[1] & 0x80 else "")
        return [Transaction("orphan", frame.start, None, frame,
                            f"a reply from {what} to no request seen: late, or its request "
                            "was not captured")]

    def _broken(self, frame: WireFrame) -> list[Transaction]:
        """Bytes that form no valid frame: the awaited reply garbled, or noise."""
        data, exp, req = frame.data, self.expect, self.pending
        if exp is not None and req is not None and len(data) >= 2 and data[0] == exp.unit \
                and data[1] & 0x7F == exp.function:
            self._clear()
            why = diagnose(data, exp) or f"garbled reply: {data.hex(' ')}"
            return [Transaction("garbled", req.start, req, frame, why)]
        if len(data) < 4 or not data.strip(b"\x00\xff"):
            return [Transaction("noise", frame.start, note=f"stray bytes {data.hex(' ')}",
                                junk=frame)]
        size = request_length(data[:11]) or reply_length(data[:11])
        if size == len(data):
            why = f"CRC error in a frame of unit {data[0]}: {data.hex(' ')}"
        elif size and size > len(data):
            why = f"truncated frame ({len(data)} of {size} bytes): {data.hex(' ')}"
        else:
            why = f"garbage: {data[:24].hex(' ')}" + (" ..." if len(data) > 24 else "")
        return [Transaction("broken", frame.start, note=why, junk=frame)]

    def _unanswered(self, why: str) -> Transaction:
        req = self.pending
        assert req is not None
        self._clear()
        return Transaction("timeout", req.start, req, None, why)

    def _clear(self) -> None:
        self.pending, self.expect = None, None


def _expect(request: bytes) -> Expect | None:
    """``expect_for`` any CRC-valid request: a read of more than a reply can carry (a
    buggy master, or noise that passes the CRC: 128 registers would need 261 bytes) can
    only be answered with an exception; its length is past any frame, so no normal
    reply is ever taken for it."""
    length = answer_length(request) or 0
    if request[1] in READ_FUNCTIONS and length > MAX_FRAME:
        return Expect(request[0], request[1], request[:2], length)
    return expect_for(request)


def _is_request(data: bytes) -> bool:
    """A complete frame shaped like a request (the function table's request length)."""
    return not data[1] & 0x80 and request_length(data[:11]) == len(data)
