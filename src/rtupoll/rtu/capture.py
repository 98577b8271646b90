"""Captured RTU bytes -> frames: CRC, function, addresses, values, exception, direction.

Pure, for ``rtupoll decode``. A capture from a sniffer or a manual has no frame
boundaries and often no timing, so a stream is split by each function's structure
and confirmed by the CRC; a frame whose CRC is wrong is still decoded (that is the
point of looking at it) and says which CRC it should carry. RTU has no direction
bit either: request or reply is inferred from the structure and from the frame
before it, and a guess is marked as one.

The decoding is the one strict parser's (``rtu.messages``: ``parse_request``, and
``parse_reply`` against the request before it), on the frame's PDU whatever its CRC;
a ``Frame`` holds the message it took (``message``) and what only a capture has (its
offset, CRC, kind and notes). What the parser refuses is shown as its bytes are laid
out, with the parser's reason.

Imports neither pymodbus nor rich, so ``decode --format json`` starts fast. The values
of a profile's fields in a frame are ``rtupoll.model.carried``'s (a layer above).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

from rtupoll.rtu import messages
from rtupoll.rtu.crc import crc16, crc_ok
from rtupoll.rtu.exception_codes import exception_name
from rtupoll.rtu.frames import Direction, lengths
from rtupoll.rtu.functions import (
    EXCEPTION_LENGTH,
    FUNCTION_NAMES,
    MAX_FRAME,
    READS,
    WRITE_FUNCTIONS,
    WRITES,
    Table,
    bits,
    words,
)


@dataclass(frozen=True)
class Frame:
    """One decoded frame. ``start``/``count`` of a reply come from its request when known."""

    offset: int  # byte position in the capture
    raw: bytes
    kind: str  # request | response | exception | noise | unknown
    unit: int | None = None
    function: int | None = None
    crc_ok: bool = False
    crc_expected: bytes = b""  # the two CRC bytes the frame should end with
    table: Table | None = None
    start: int | None = None
    count: int | None = None
    values: tuple[int, ...] = ()  # registers (or bits) read or written
    exception: int | None = None
    notes: tuple[str, ...] = ()
    # the typed message (``rtu.messages``) where the strict parser takes the frame
    message: messages.Request | messages.Reply | None = field(default=None, compare=False)

    @property
    def function_name(self) -> str:
        if self.function is None:
            return ""
        if self.function & 0x80:
            base = self.function & 0x7F
            return f"exception to {base:#04x} {FUNCTION_NAMES.get(base, 'unknown function')}"
        return FUNCTION_NAMES.get(self.function, "unknown function")

    @property
    def crc_found(self) -> bytes:
        return self.raw[-2:] if len(self.raw) >= 4 else b""


def parse_hex(parts: Iterable[str]) -> list[bytes]:
    """Hex text -> byte chunks. Accepts ``01 04``, ``0x01,0x04``, ``0104``, ``01:04``.

    A ``/`` token (or, for input read line by line, a new line) ends a chunk, for when
    the user knows where frames end; each chunk is still split by structure and CRC.
    ``ValueError`` says what is not hex.
    """
    chunks: list[bytes] = []
    current = bytearray()
    for part in parts:
        for token in re.split(r"[\s,;:]+", part.strip()):
            if not token:
                continue
            if token == "/":
                if current:
                    chunks.append(bytes(current))
                current = bytearray()
                continue
            digits = token[2:] if token.lower().startswith("0x") else token
            if len(digits) == 1:
                digits = "0" + digits
            if len(digits) % 2 or not re.fullmatch(r"[0-9A-Fa-f]+", digits):
                raise ValueError(f"{token!r} is not hex bytes (e.g. 01 04 00 06 or 0x01,0x04)")
            current += bytes.fromhex(digits)
    if current:
        chunks.append(bytes(current))
    if not chunks:
        raise ValueError("no bytes given")
    return chunks


def _lengths(data: bytes) -> list[tuple[int, str]]:
    """The frame lengths the function code allows at the start of ``data``, with the kind
    (from the function table; a write's echo is settled from context)."""
    if len(data) < 2:
        return []
    if data[1] & 0x80:
        return [(EXCEPTION_LENGTH, "exception")]
    if data[1] not in READS and data[1] not in WRITE_FUNCTIONS:
        return []
    head = data[:11]
    options = [(n, kind) for direction, kind in ((Direction.REQUEST, "request"),
                                                 (Direction.REPLY, "response"))
               for n in lengths(head, direction)]
    if data[1] in (15, 16):  # the 8-byte echo first: a request carries its data
        options.reverse()
    out: list[tuple[int, str]] = []
    for n, kind in options:
        if all(n != m for m, _ in out):
            out.append((n, kind))
    return out


def split(data: bytes, *, base: int = 0) -> list[tuple[int, bytes, str | None]]:
    """A stream -> (offset, bytes, structural kind or None) per frame, confirmed by CRC.

    At each position a structural length whose CRC checks wins; failing that, a stray
    byte or two (RS-485 direction switching leaves 0x00/0xFF) is skipped if a valid
    frame follows; failing that, any length with a valid CRC; failing that, the
    structural length is taken with its CRC wrong, or the rest as one unknown frame.
    """
    frames: list[tuple[int, bytes, str | None]] = []
    i = 0
    while i < len(data):
        rest = data[i:]
        valid = [(n, k) for n, k in _lengths(rest) if 4 <= n <= len(rest) and crc_ok(rest[:n])]
        if valid:
            n, kind = _prefer(valid, frames)
            frames.append((base + i, rest[:n], kind))
            i += n
            continue
        skip = next((s for s in (1, 2) if s < len(rest) and any(
            4 <= n <= len(rest) - s and crc_ok(rest[s : s + n])
            for n, _ in _lengths(rest[s:]))), 0)
        if skip:
            frames.append((base + i, rest[:skip], "noise"))
            i += skip
            continue
        anylen = next((n for n in range(4, min(len(rest), MAX_FRAME) + 1)
                       if crc_ok(rest[:n])), 0)
        if anylen:
            frames.append((base + i, rest[:anylen], None))
            i += anylen
            continue
        fitting = [(n, k) for n, k in _lengths(rest) if 4 <= n <= len(rest)]
        if fitting:
            n, kind = _prefer(fitting, frames)
            frames.append((base + i, rest[:n], kind))
            i += n
            continue
        frames.append((base + i, rest, None))
        break
    return frames


def _prefer(options: list[tuple[int, str]], before: list[tuple[int, bytes, str | None]]
            ) -> tuple[int, str]:
    """Two structures fit (a coil read's request and a 3-byte reply): the frame before decides."""
    if len(options) > 1 and before and before[-1][2] == "request":
        return next((o for o in options if o[1] == "response"), options[0])
    return options[0]


def _crc_bytes(body: bytes) -> bytes:
    return struct.pack("<H", crc16(body))


def decode_stream(chunks: Sequence[bytes], *, start: int | None = None) -> list[Frame]:
    """Every frame in the capture, each reply tied to the request before it.

    ``start`` is the register address of a reply whose request was not captured.
    """
    frames: list[Frame] = []
    offset = 0
    for chunk in chunks:
        for pos, raw, kind in split(chunk, base=offset):
            prev = next((f for f in reversed(frames) if f.kind != "noise"), None)
            frames.append(decode_frame(raw, kind, prev, offset=pos, start=start))
        offset += len(chunk)
    return frames


def decode_frame(raw: bytes, kind: str | None = None, prev: Frame | None = None, *,
                 offset: int = 0, start: int | None = None) -> Frame:
    """One frame. ``kind`` is what the splitter saw; ``prev`` the frame just before it.

    What the one strict parser (``rtu.messages``) takes is decoded from its message (the
    frame's ``message``), whatever its CRC, which the frame shows apart; what it refuses
    is still shown as its bytes are laid out, with the parser's reason."""
    if kind == "noise" or len(raw) < 4:
        what = "stray byte(s) between frames (typical of RS-485 direction switching)" \
            if kind == "noise" else "too short for a frame (address, function, CRC)"
        return Frame(offset, raw, "noise", notes=(what,))
    unit, fc = raw[0], raw[1]
    expected = _crc_bytes(raw[:-2])
    ok = expected == raw[-2:]
    notes = [] if ok else _crc_hints(raw, expected)
    base = Frame(offset, raw, "unknown", unit, fc, ok, expected)
    pending = prev if prev is not None and prev.kind == "request" and prev.unit == unit \
        and prev.function == (fc & 0x7F) else None
    asked = pending.message if pending is not None and isinstance(
        pending.message, messages.TableRequest) else None
    body = raw[2:-2]
    if fc & 0x80:
        code = body[0] if body else None
        if len(raw) != 5:
            notes.append(f"an exception reply is 5 bytes, this is {len(raw)}")
        if fc & 0x7F not in FUNCTION_NAMES:
            notes.append(f"{fc:#04x} is an exception to {fc & 0x7F:#04x}, not a standard function")
        if prev is not None and prev.kind == "request" and prev.unit == unit \
                and prev.function != fc & 0x7F and prev.function is not None:
            right = messages.ExceptionReply(unit, prev.function, body[0] if body else 0)
            notes.append(f"the request before it was function {prev.function:#04x}: an exception "
                         f"reply to that carries {prev.function | 0x80:#04x}, not {fc:#04x} "
                         f"({right.frame().hex(' ').upper()})")
        if code is not None:
            notes.append(f"exception {code:02d}: {exception_name(code)}")
        return replace(base, kind="exception", exception=code, notes=tuple(notes),
                       message=messages.ExceptionReply(unit, fc & 0x7F, code)
                       if len(raw) == 5 and code is not None else None)
    if fc in READS:
        return _read(raw, kind, pending, asked, notes, base, start)
    if fc in (5, 6):
        if len(raw) != 8:
            notes.append(_odd_write_reply(raw, fc))
            return replace(base, kind="response" if pending else "unknown", notes=tuple(notes),
                           values=words(body[1:]) if len(body) >= 1 else ())
        request = _request(raw, notes)  # a request and its echo are the same bytes
        reply = _reply(asked, raw)
        # (both CRCs good: an echo is the very frame; a refused request's: its bytes again)
        echo = isinstance(reply, messages.WriteReply) and ok and pending is not None and \
            pending.crc_ok if asked is not None else pending is not None and pending.raw == raw
        if echo:
            notes.insert(len(notes) - (request is None), "an echo of the request: the write "
                         "was accepted")
        elif pending is None:
            notes.insert(len(notes) - (request is None), "a write request, or its echo (the "
                         "reply repeats the request)")
        else:
            notes.insert(len(notes) - (request is None), "not an echo of the request before it")
        address, value = struct.unpack(">HH", body)
        vals = request.values if isinstance(request, messages.WriteSingle) else \
            ((1 if value == 0xFF00 else 0),) if fc == 5 else (value,)
        return replace(base, kind="response" if pending else "request", table=WRITES[fc],
                       start=address, count=1, values=vals, notes=tuple(notes),
                       message=reply if pending else request)
    if fc in (15, 16):
        table = WRITES[fc]
        if len(raw) == 8:
            reply = _reply(asked, raw)
            address, qty = struct.unpack(">HH", body[:4])
            return replace(base, kind="response", table=table, start=address, count=qty,
                           notes=tuple(notes), message=reply)
        request = _request(raw, notes)
        if isinstance(request, messages.WriteMultiple):
            return replace(base, kind="request", table=table, start=request.address,
                           count=request.count, values=request.values, notes=tuple(notes),
                           message=request)
        # refused: laid out as it is
        address, qty = struct.unpack(">HH", body[:4]) if len(body) >= 4 else (None, None)
        data = body[5:]
        data_values = bits(data, qty or 0) if fc == 15 else words(data)
        return replace(base, kind="request", table=table, start=address, count=qty,
                       values=data_values, notes=tuple(notes))
    notes.append(f"function {fc:#04x} is not one rtupoll decodes; data {body.hex(' ').upper()}")
    return replace(base, kind="unknown", notes=tuple(notes))


def _request(raw: bytes, notes: list[str]) -> messages.Request | None:
    """The request the frame's PDU is (the one strict parser, ``rtu.messages``; its CRC
    is the frame's own business), or None with the parser's reason in ``notes``."""
    try:
        return messages.parse_request(raw[1:-2], unit=raw[0])
    except messages.Malformed as bad:
        notes.append(bad.reason)
        return None


def _reply(asked: messages.Request | None, raw: bytes) -> messages.Reply | None:
    """The reply the frame is to the request before it (``messages.parse_reply``), or
    None: no request, or no answer to it."""
    if asked is None:
        return None
    try:
        return messages.parse_reply(asked, raw[1:-2], unit=raw[0])
    except messages.Malformed:
        return None


def _read(raw: bytes, kind: str | None, pending: Frame | None,
          asked: messages.Request | None, notes: list[str], base: Frame, start: int | None
          ) -> Frame:
    fc, body = raw[1], raw[2:-2]
    table = READS[fc]
    as_request = len(raw) == 8 and (kind == "request" or (kind is None and pending is None))
    if as_request:
        request = _request(raw, notes)
        if isinstance(request, messages.ReadRequest):
            address, qty = request.address, request.count
        else:  # refused: laid out as it is
            address, qty = struct.unpack(">HH", body)
        if not table.is_register and kind == "request" and pending is None and 5 + raw[2] == 8:
            notes.append("could also be a reply carrying 3 bytes of bits")
        return replace(base, kind="request", table=table, start=address, count=qty,
                       notes=tuple(notes), message=request)
    reply = _reply(asked, raw)
    if isinstance(reply, messages.ReadReply) and isinstance(asked, messages.ReadRequest):
        return replace(base, kind="response", table=table, start=asked.address,
                       count=asked.count, values=reply.values, notes=tuple(notes),
                       message=reply)
    # no request before it, or no answer to it: laid out as it is
    nbytes, data = (body[0], body[1:]) if body else (0, b"")
    if nbytes != len(data):
        notes.append(f"byte count says {nbytes}, {len(data)} data bytes follow")
    if pending is not None:
        start = pending.start
        expect = 2 * (pending.count or 0) if table.is_register else ((pending.count or 0) + 7) // 8
        if expect != len(data):
            notes.append(f"the request asked for {pending.count}, which is {expect} bytes")
    if table.is_register:
        if len(data) % 2:
            notes.append("an odd number of data bytes cannot be registers")
        values = words(data)
        count: int | None = len(values)
    else:
        count = pending.count if pending is not None else None
        values = bits(data, count if count is not None else 8 * len(data))
    return replace(base, kind="response", table=table, start=start, count=count, values=values,
                   notes=tuple(notes))


def _odd_write_reply(raw: bytes, fc: int) -> str:
    text = f"function {fc:02d} frames (request and its echo) are 8 bytes, this is {len(raw)}"
    body = raw[2:-2]
    if body and body[0] == len(body) - 1:
        text += (f"; it is laid out like a read reply (byte count {body[0]}, "
                 f"data {body[1:].hex(' ').upper()}), not an echo: treat the write as unconfirmed "
                 "and read the register back")
    return text


def _crc_hints(raw: bytes, expected: bytes) -> list[str]:
    found = raw[-2:]
    hints = [f"CRC {found.hex(' ').upper()} is wrong: expected {expected.hex(' ').upper()}"]
    if found == expected[::-1]:
        hints.append("the CRC bytes are swapped (sent high byte first)")
    elif len(raw) == 8 and raw[1] in (1, 2, 3, 4, 5, 6):
        head, (address, value) = raw[:2], struct.unpack(">HH", raw[2:6])
        for delta in (1, -1, 2, -2, 3, -3):
            other = head + struct.pack(">HH", (address + delta) & 0xFFFF, value)
            if _crc_bytes(other) == found:
                hints.append(f"{found.hex(' ').upper()} is the CRC of the same request for address "
                             f"{(address + delta) & 0xFFFF:#06x}: a copied row or a shifted "
                             f"table?")
                break
    return hints
