"""Where a frame ends: the one frame-finding primitive, from the function table and the CRC.

RTU has no delimiter but silence, and silence is not always seen (a TCP stream, a
capture file, a busy line), so every reader finds frames by structure: the function
code (and, for some, a byte count) gives the length, the CRC confirms it. ``frame_at``
says, for the bytes at one position, one of three things:

- ``n > 0``: a complete frame of ``n`` bytes with a good CRC starts here;
- ``NEED_MORE``: the bytes so far may still become one (the byte count, or the rest of
  a likely length, has not arrived);
- ``NOT_A_FRAME``: no length the table allows here ends in a good CRC.

What is likely depends on what the reader knows: the direction (a request, a reply, or
either for a tap that hears both) and, for a reply, the request it answers. Each reader
keeps its own policy on top: the gateway's RTU-over-TCP framer is strict (not a frame:
close the connection), the simulator's receiver drops a byte and looks again, the
sniffer resynchronises and reads gaps, ``decode`` guesses from the frame before.
"""

from __future__ import annotations

import enum
from typing import Final

from rtupoll.rtu.crc import crc_ok
from rtupoll.rtu.functions import EXCEPTION_LENGTH, FUNCTIONS, MAX_FRAME, answer_length

NEED_MORE: Final = 0
NOT_A_FRAME: Final = -1


class Direction(enum.Enum):
    REQUEST = "request"
    REPLY = "reply"
    EITHER = "either"  # a tap on the line: a request or a reply


# the lengths the table knows for each function, by direction (a free length is left out)
_KNOWN: dict[Direction, dict[int, tuple[tuple[int, int], ...]]] = {
    d: {fc: tuple((length.fixed, length.count_at) for length in kinds if length.known)
        for fc, fn in FUNCTIONS.items()
        for kinds in [{Direction.REQUEST: (fn.request,), Direction.REPLY: (fn.reply,),
                       Direction.EITHER: (fn.request, fn.reply)}[d]]}
    for d in Direction}


def lengths(head: bytes, direction: Direction, answering: bytes | None = None
            ) -> tuple[int, ...]:
    """The frame lengths the table allows at ``head`` (its first 11 bytes suffice),
    likeliest first. A length whose byte count has not arrived (and any length, before
    the function code has) counts as ``len(head) + 1``: more than is there.

    ``answering`` (the request frame a reply is awaited for) puts its normal reply's
    length, or its exception's, first."""
    more = len(head) + 1
    if more < 3:
        return (more,)
    fc = head[1]
    out: list[int] = []
    if answering is not None and direction is not Direction.REQUEST and head[0] == answering[0]:
        if fc == answering[1]:
            n = answer_length(answering)
            if n is not None:
                out.append(n)
        elif fc == answering[1] | 0x80:
            out.append(EXCEPTION_LENGTH)
    if fc & 0x80:
        if direction is not Direction.REQUEST and fc & 0x7F in FUNCTIONS:
            out.append(EXCEPTION_LENGTH)
    else:
        for fixed, count_at in _KNOWN[direction].get(fc, ()):
            out.append(fixed or (count_at + 3 + head[count_at] if more > count_at + 1
                                 else more))
    kept: list[int] = []
    for n in out:
        if (4 <= n <= MAX_FRAME or n == more) and n not in kept:
            kept.append(n)
    return tuple(kept)


def frame_at(buf: bytes | bytearray, at: int = 0, *, direction: Direction,
             answering: bytes | None = None, final: bool = False) -> int:
    """The length of the CRC-valid frame at ``buf[at]``, ``NEED_MORE`` or ``NOT_A_FRAME``.

    Lengths are tried likeliest first; one not complete yet means ``NEED_MORE`` (a
    request whose first bytes happen to make a CRC-valid shorter frame must not be cut
    there), unless ``final``: no more bytes will come, so only what is here counts."""
    for n in lengths(bytes(buf[at : at + 11]), direction, answering):
        if at + n > len(buf):
            if final:
                continue
            return NEED_MORE
        if crc_ok(bytes(buf[at : at + n])):
            return n
    return NOT_A_FRAME
