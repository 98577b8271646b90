"""Which bytes answer a request: RTU reply matching and diagnosis, pure.

RTU frames carry no length field and no transaction id, so a master that reads a
byte stream has to know what it is waiting for. Here that knowledge comes from the
request's own bytes (``expect_for``): the reply must come from the same unit, carry
the same function (or its exception, function | 0x80), and either the byte count a
read of that many registers/bits produces or, for a write, the exact echo of the
address and value/quantity. ``find_reply`` finds such a frame, with a valid CRC,
anywhere in what arrived -- after stray bytes (0x00/0xFF from RS-485 direction
switching), after another unit's reply, after garbage -- so nothing before it can
make the master drop or misread it. ``diagnose`` says, for an attempt that got no
answer, whether what did arrive was a broken reply (``FrameError``: CRC error,
truncated, mismatched, garbage) or nothing that matters (silence, line noise, other
units' whole frames: a timeout).

``rtupoll.io.bus`` uses these on every receive; the simulator and tests may use them to
reason about a wire capture.
"""

from __future__ import annotations

from rtupoll.frozen import frozen
from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.functions import (
    EXCEPTION_LENGTH,
    MAX_FRAME,
    READ_FUNCTIONS,
    answer_length,
    reply_length,
)


@frozen
class Expect:
    """The answer one request allows: a normal reply or the function's exception reply."""

    unit: int
    function: int
    prefix: bytes  # a normal reply starts with these: unit, function, byte count / echo
    length: int  # of a normal reply, CRC included; 0: as the reply's own bytes say

    def size(self, head: bytes) -> int | None:
        """How long the normal reply starting with ``head`` is (None: not known yet)."""
        return self.length or reply_length(head)


def expect_for(request: bytes) -> Expect | None:
    """What must answer ``request`` (an RTU frame); None for a broadcast."""
    unit, fn = request[0], request[1]
    if unit == 0:
        return None
    length = answer_length(request)
    if fn in READ_FUNCTIONS:
        assert length is not None
        return Expect(unit, fn, bytes((unit, fn, length - 5)), length)
    if fn in (5, 6, 15, 16, 22):  # they echo the address and the value, quantity or masks
        return Expect(unit, fn, request[:6], length or 8)
    if fn == 8:  # the sub-function comes back; its data only for some (an echo)
        return Expect(unit, fn, request[:4], length or 8)
    if fn == 43:  # the MEI type and, for device identification, the code come back
        return Expect(unit, fn, request[:4] if request[2:3] == b"\x0e" else request[:3],
                      0)
    return Expect(unit, fn, request[:2], length or 0)  # its length in its own bytes


def answers(frame: bytes, exp: Expect) -> bool:
    """A complete frame (CRC checked by the caller) has the shape of ``exp``'s answer:
    the normal reply, or the function's exception reply."""
    if frame[0] != exp.unit:
        return False
    if frame[1] == exp.function | 0x80:
        return len(frame) == EXCEPTION_LENGTH
    return len(frame) == exp.size(frame) and frame.startswith(exp.prefix)


def find_reply(buf: bytes, exp: Expect) -> bytes | None:
    """The first CRC-valid frame in ``buf`` that answers ``exp``, wherever it starts."""
    error = bytes((exp.unit, exp.function | 0x80))
    i = buf.find(exp.prefix[:1])
    while 0 <= i <= len(buf) - 5:
        rest = buf[i : i + MAX_FRAME]
        for head, size in ((exp.prefix, exp.size(rest)), (error, EXCEPTION_LENGTH)):
            frame = rest[:size] if size else b""
            if len(frame) == size and frame.startswith(head) and crc_ok(frame):
                return frame
        i = buf.find(exp.prefix[:1], i + 1)
    return None


def diagnose(buf: bytes, exp: Expect | None) -> str | None:
    """Why the bytes of an unanswered attempt are a garbled reply (``FrameError``), or
    None when they are silence, line noise (0x00/0xFF) or other units' whole frames."""
    if exp is None or not buf or find_reply(buf, exp):  # (the answer, just at the deadline)
        return None
    junk, i = bytearray(), 0
    while i < len(buf):
        size = reply_length(buf[i : i + MAX_FRAME])
        if size and i + size <= len(buf) and crc_ok(buf[i : i + size]):
            frame = buf[i : i + size]
            if frame[0] == exp.unit and frame[1] & 0x7F == exp.function:
                expected = f"{exp.length} bytes starting" if exp.length else "starting"
                return (f"reply does not match the request (expected {expected} "
                        f"{exp.prefix.hex(' ')}): {_hex(frame)}")
            i += size  # a whole frame from another unit: not ours, and not garbage
            continue
        junk.append(buf[i])
        i += 1
    for fn in (exp.function, exp.function | 0x80):
        at = junk.find(bytes((exp.unit, fn)))
        if at >= 0:
            rest = bytes(junk[at:])
            size = reply_length(rest[:MAX_FRAME]) or exp.length
            if not size:
                return f"garbled reply: {_hex(rest)}"
            if len(rest) < size:
                return f"truncated reply ({len(rest)} of {size} bytes): {_hex(rest)}"
            return f"CRC error in reply: {_hex(rest[:size])}"
    return f"garbled reply: {_hex(bytes(junk))}" if len(junk.strip(b"\x00\xff")) >= 3 else None


def _hex(data: bytes) -> str:
    return data[:24].hex(" ") + (" ..." if len(data) > 24 else "")
