"""Modbus requests and replies as typed values, sans-IO: bytes in, a message or a
refusal out (as h11 has ``Request``/``Response`` events).

One strict parser for each direction, both checked against the one function table
(``functions``: lengths, quantities, byte counts):

- ``parse_request(data)``: an RTU frame (unit, PDU, CRC), or with ``unit=`` a bare PDU
  (Modbus TCP carries the unit apart), -> ``ReadRequest``, ``WriteSingle``,
  ``WriteMultiple`` or ``OtherRequest`` (every other function of the table, its data
  kept raw);
- ``parse_reply(request, data)``: what answers that request -> ``ReadReply``,
  ``WriteReply``, ``ExceptionReply`` or ``OtherReply``.

Anything else raises ``Malformed`` with a reason in words and the exception ``code`` a
Modbus server answers for it (None: a server stays silent, as for a CRC error). No other
exception escapes either parser, whatever the bytes. Every message encodes back to the
bytes it was parsed from (``pdu()``, ``frame()``).

The one set of message types, on every side: the master builds its requests as them
(``rtu.transaction.read_request``, ...) and parses its answers with ``parse_reply``; the
gateway and the simulator answer with the replies' own ``pdu()``/``frame()`` (the one
reply encoder); the sniffer and ``decode`` (``rtu.capture``) parse with the same two
parsers. Each caller keeps its own policy on top: the gateway answers the code, the
simulator answers it as its device would, the sniffer shows the function with no values.
"""

from __future__ import annotations

import struct

from rtupoll.frozen import frozen
from rtupoll.rtu.crc import crc_ok, with_crc
from rtupoll.rtu.exception_codes import ExceptionCode, exception_name
from rtupoll.rtu.functions import (
    FUNCTIONS,
    MAX_QUANTITY,
    READS,
    TABLES,
    Table,
    bits,
    data_bytes,
    pack_bits,
    words,
)

COIL_ON, COIL_OFF = 0xFF00, 0x0000


class Malformed(ValueError):
    """Bytes that are no valid message: ``reason`` in words; ``code`` the exception a
    server answers (None: it answers nothing); ``unit`` and ``function`` where known."""

    def __init__(self, reason: str, code: int | None = ExceptionCode.ILLEGAL_VALUE, *,
                 unit: int | None = None, function: int | None = None) -> None:
        super().__init__(reason)
        self.reason, self.code, self.unit, self.function = reason, code, unit, function


class _Message:
    """What every message has: a unit, a function code, and its own bytes."""

    __slots__ = ()
    unit: int
    function: int

    def pdu(self) -> bytes:
        raise NotImplementedError

    def frame(self) -> bytes:
        """The RTU frame: unit, PDU, CRC."""
        return with_crc(bytes((self.unit,)) + self.pdu())


# -- requests ---------------------------------------------------------------------------

@frozen(slots=True)
class ReadRequest(_Message):
    """Read ``count`` coils (1), discrete inputs (2), holding (3) or input (4) registers."""

    unit: int
    function: int
    address: int
    count: int

    @property
    def table(self) -> Table:
        return READS[self.function]

    def pdu(self) -> bytes:
        return struct.pack(">BHH", self.function, self.address, self.count)

    def frame(self) -> bytes:  # (one struct call: the master sends one a transaction)
        return with_crc(struct.pack(">BBHH", self.unit, self.function, self.address,
                                    self.count))


@frozen(slots=True)
class WriteSingle(_Message):
    """Write one coil (5: ``value`` 1 or 0) or one holding register (6: the word)."""

    unit: int
    function: int
    address: int
    value: int

    @property
    def table(self) -> Table:
        return TABLES[self.function]

    @property
    def count(self) -> int:
        return 1

    @property
    def values(self) -> tuple[int, ...]:
        return (self.value,)

    def pdu(self) -> bytes:
        word = (COIL_ON if self.value else COIL_OFF) if self.function == 5 else self.value
        return struct.pack(">BHH", self.function, self.address, word)


@frozen(slots=True)
class WriteMultiple(_Message):
    """Write coils (15: ``values`` 1 or 0) or holding registers (16) from ``address`` on."""

    unit: int
    function: int
    address: int
    values: tuple[int, ...]

    @property
    def table(self) -> Table:
        return TABLES[self.function]

    @property
    def count(self) -> int:
        return len(self.values)

    def pdu(self) -> bytes:
        data = pack_bits(self.values) if self.function == 15 else \
            b"".join(struct.pack(">H", v) for v in self.values)
        return struct.pack(">BHHB", self.function, self.address, self.count, len(data)) + data


@frozen(slots=True)
class OtherRequest(_Message):
    """Any other function of the table (diagnostics, ids, FIFO, ...): its data kept raw."""

    unit: int
    function: int
    data: bytes

    def pdu(self) -> bytes:
        return bytes((self.function,)) + self.data


Request = ReadRequest | WriteSingle | WriteMultiple | OtherRequest
# the requests that address a run of one table: ``table``, ``address``, ``count``
TableRequest = ReadRequest | WriteSingle | WriteMultiple


# -- replies ----------------------------------------------------------------------------

@frozen(slots=True)
class ReadReply(_Message):
    """The registers (3, 4) or the requested number of bits (1, 2) a read returned."""

    unit: int
    function: int
    values: tuple[int, ...]

    def pdu(self) -> bytes:
        values = self.values
        if self.function in (1, 2):
            data = pack_bits(values)
            return bytes((self.function, len(data))) + data
        n = len(values)  # (one struct call: the gateway and the simulator answer with it)
        return struct.pack(f">BB{n}H", self.function, 2 * n, *values)


@frozen(slots=True)
class WriteReply(_Message):
    """A write's confirmation: the echo of 5/6 (``value`` as in the request) or the
    address and quantity of 15/16 (``value`` is the quantity)."""

    unit: int
    function: int
    address: int
    value: int

    def pdu(self) -> bytes:
        return WriteSingle(self.unit, self.function, self.address, self.value).pdu() \
            if self.function in (5, 6) else \
            struct.pack(">BHH", self.function, self.address, self.value)


@frozen(slots=True)
class ExceptionReply(_Message):
    """The device refused ``function`` (the request's, without 0x80) with ``code``."""

    unit: int
    function: int
    code: int

    @property
    def name(self) -> str:
        return exception_name(self.code)

    def pdu(self) -> bytes:
        return bytes((self.function | 0x80, self.code))


@frozen(slots=True)
class OtherReply(_Message):
    """The normal reply to an ``OtherRequest``: its data kept raw."""

    unit: int
    function: int
    data: bytes

    def pdu(self) -> bytes:
        return bytes((self.function,)) + self.data


Reply = ReadReply | WriteReply | ExceptionReply | OtherReply


# -- parsing ----------------------------------------------------------------------------

def _split(data: bytes, unit: int | None, what: str) -> tuple[int, bytes]:
    """(unit, PDU) of an RTU frame (CRC checked) or of a bare PDU with its ``unit``."""
    if unit is not None:
        return unit, data
    if len(data) < 4:
        raise Malformed(f"{len(data)} bytes are too short for a {what} (unit, function, "
                        "CRC)", None)
    if not crc_ok(data):
        raise Malformed(f"CRC error in {data[:24].hex(' ')}", None, unit=data[0],
                        function=data[1])
    return data[0], data[1:-2]


def parse_request(data: bytes, *, unit: int | None = None) -> Request:
    """The request an RTU frame carries (CRC checked), or with ``unit`` a bare PDU.

    Raises ``Malformed`` (with the exception code a server answers) for anything that is
    not a complete request of a function in the table: unknown function, wrong length,
    quantity outside the function's limit, a run past 0xFFFF, a byte count that does not
    fit, a coil value that is neither ON nor OFF."""
    if unit is None:
        unit, pdu = _split(data, unit, "request")
    else:
        pdu = data
    if not pdu:
        raise Malformed("empty PDU", ExceptionCode.ILLEGAL_FUNCTION, unit=unit)
    fc = pdu[0]
    fn = FUNCTIONS.get(fc)
    if fn is None or fc & 0x80:
        raise Malformed(f"function {fc} is not a Modbus request rtupoll passes on",
                        ExceptionCode.ILLEGAL_FUNCTION, unit=unit, function=fc)
    want = fn.request.fixed or fn.request.of(b"\x00" + pdu[:10])
    if want is None:
        raise Malformed(f"{fn.name}: truncated ({len(pdu)} bytes)", unit=unit, function=fc)
    if want - 3 != len(pdu):
        raise Malformed(f"{fn.name}: {len(pdu)} bytes, the function takes {want - 3}",
                        unit=unit, function=fc)
    if fc not in TABLES:
        return OtherRequest(unit, fc, pdu[1:])
    address, n = struct.unpack_from(">HH", pdu, 1)
    if fc == 6:
        return WriteSingle(unit, fc, address, n)
    if fc == 5:
        if n not in (COIL_OFF, COIL_ON):
            raise Malformed(f"coil value 0x{n:04X} is neither ON nor OFF", unit=unit,
                            function=fc)
        return WriteSingle(unit, fc, address, int(n == COIL_ON))
    limit = MAX_QUANTITY[fc]
    if not 1 <= n <= limit:
        raise Malformed(f"{fn.name}: quantity {n} is outside 1..{limit}", unit=unit,
                        function=fc)
    if address + n > 0x10000:
        raise Malformed(f"0x{address:04X} + {n} runs past 0xFFFF", ExceptionCode.ILLEGAL_ADDRESS,
                        unit=unit, function=fc)
    if fc in READS:
        return ReadRequest(unit, fc, address, n)
    size = pdu[5]
    if size != data_bytes(1 if fc == 15 else 3, n):
        raise Malformed(f"byte count {size} does not fit quantity {n}", unit=unit,
                        function=fc)
    return WriteMultiple(unit, fc, address, bits(pdu[6:], n) if fc == 15 else words(pdu[6:]))


def parse_reply(request: Request, data: bytes, *, unit: int | None = None) -> Reply:
    """What ``data`` (an RTU frame, or with ``unit`` a bare PDU) says in answer to
    ``request``; ``Malformed`` when it is no answer to it (``code`` None: a master
    answers nothing, it only refuses the reply)."""
    got, pdu = _split(data, unit, "reply")
    if got != request.unit:
        raise _refused(f"unit {got} answers a request to unit {request.unit}", got, pdu)
    if not pdu:
        raise _refused("empty PDU", got, pdu)
    fc = pdu[0]
    if fc == request.function and type(request) is ReadRequest:  # (the master's every read)
        n = request.count
        size = 2 * n if fc > 2 else (n + 7) // 8
        if len(pdu) != 2 + size or pdu[1] != size:
            raise _refused(f"a reply to a read of {n} carries {size} data bytes, this has "
                           f"{len(pdu) - 2} (byte count {pdu[1] if len(pdu) > 1 else '-'})",
                           got, pdu)
        return ReadReply(got, fc, struct.unpack_from(f">{n}H", pdu, 2) if fc > 2
                         else bits(pdu[2:], n))
    if fc == request.function | 0x80:
        if len(pdu) != 2:
            raise _refused(f"an exception reply is 2 PDU bytes, this is {len(pdu)}", got, pdu)
        return ExceptionReply(got, request.function, pdu[1])
    if fc != request.function:
        raise _refused(f"function {fc} does not answer function {request.function}", got, pdu)
    if isinstance(request, WriteSingle | WriteMultiple):
        expected = request.pdu()[:5]
        if pdu != expected:
            raise _refused(f"not the confirmation of the write ({expected.hex(' ')}): "
                           f"{pdu[:24].hex(' ')}", got, pdu)
        return WriteReply(got, fc, request.address,
                          request.value if isinstance(request, WriteSingle) else request.count)
    length = FUNCTIONS[fc].reply
    want = length.of(b"\x00" + pdu[:3])
    if length.known and (want is None or want - 3 != len(pdu)):
        raise _refused(f"{FUNCTIONS[fc].name}: {len(pdu)} reply bytes, the function takes "
                       f"{'more' if want is None else want - 3}", got, pdu)
    return OtherReply(got, fc, pdu[1:])


def _refused(reason: str, unit: int, pdu: bytes) -> Malformed:
    """A reply refused: a master answers nothing (``code`` None)."""
    return Malformed(reason, None, unit=unit, function=pdu[0] if pdu else None)
