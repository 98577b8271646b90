"""The Modbus RTU function table: names, frame lengths per function code, data packing.

The one place that knows how long a frame is. A frame is ``unit, function, data, CRC``;
its length follows from the function code and, for some, a byte count inside the frame
(``Length``). Requests and normal replies of one function differ, so each function
has one ``Length`` for each; an exception reply (function | 0x80) is always 5 bytes.
The bus (to know the answer it awaits), the simulator's receiver, ``decode`` and the
sniffer all take their lengths from ``FUNCTIONS``.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Sequence

from rtupoll.frozen import frozen

MAX_FRAME = 256  # the RTU maximum, address to CRC
MAX_PDU = MAX_FRAME - 3  # function and data: the frame without unit and CRC
EXCEPTION_LENGTH = 5  # unit, function | 0x80, code, CRC
MAX_BITS = 2000  # coils or discrete inputs in one read (FC01/02)
MAX_REGISTERS = 125  # registers in one read (FC03/04)
MAX_WRITE_BITS = 1968  # coils in one write (FC15)
MAX_WRITE_REGISTERS = 123  # registers in one write (FC16)


class Table(str, enum.Enum):
    """The four Modbus data tables."""

    COIL = "coil"
    DISCRETE = "discrete"
    INPUT = "input"
    HOLDING = "holding"

    @property
    def read_function(self) -> int:
        return {"coil": 1, "discrete": 2, "input": 4, "holding": 3}[self.value]

    @property
    def is_register(self) -> bool:
        return self in (Table.INPUT, Table.HOLDING)

    @property
    def modicon_base(self) -> int:
        """The Modicon reference prefix: 0xxxx coils, 1xxxx, 3xxxx inputs, 4xxxx holding."""
        return {"coil": 0, "discrete": 10000, "input": 30000, "holding": 40000}[self.value]



@frozen
class Length:
    """How long a frame is: ``fixed`` bytes, or a byte count at ``count_at`` plus
    ``count_at + 1`` header bytes and the CRC. ``known`` is False where the standard
    leaves the length to the data (a function rtupoll only passes through)."""

    fixed: int = 0
    count_at: int = 0

    @property
    def known(self) -> bool:
        return bool(self.fixed or self.count_at)

    def of(self, head: bytes) -> int | None:
        """The frame's length from its first bytes; None until the count byte is in."""
        if self.fixed:
            return self.fixed
        if self.count_at and len(head) > self.count_at:
            return self.count_at + 1 + head[self.count_at] + 2
        return None


@frozen
class Function:
    code: int
    name: str
    request: Length
    reply: Length


_FIXED8 = Length(8)
FUNCTIONS: dict[int, Function] = {f.code: f for f in (
    Function(1, "read coils", _FIXED8, Length(count_at=2)),
    Function(2, "read discrete inputs", _FIXED8, Length(count_at=2)),
    Function(3, "read holding registers", _FIXED8, Length(count_at=2)),
    Function(4, "read input registers", _FIXED8, Length(count_at=2)),
    Function(5, "write single coil", _FIXED8, _FIXED8),
    Function(6, "write single register", _FIXED8, _FIXED8),
    Function(7, "read exception status", Length(4), Length(5)),
    Function(8, "diagnostics", _FIXED8, _FIXED8),
    Function(11, "get comm event counter", Length(4), _FIXED8),
    Function(12, "get comm event log", Length(4), Length(count_at=2)),
    Function(15, "write multiple coils", Length(count_at=6), _FIXED8),
    Function(16, "write multiple registers", Length(count_at=6), _FIXED8),
    Function(17, "report server id", Length(4), Length(count_at=2)),
    Function(22, "mask write register", Length(10), Length(10)),
    Function(23, "read/write multiple registers", Length(count_at=10), Length(count_at=2)),
    Function(24, "read FIFO queue", Length(6), Length()),
    Function(43, "encapsulated interface", Length(7), Length()),
)}
FUNCTION_NAMES: dict[int, str] = {f.code: f.name for f in FUNCTIONS.values()}
READ_FUNCTIONS = (1, 2, 3, 4)
WRITE_FUNCTIONS = (5, 6, 15, 16)
# the table each read, and each write, function addresses
READS: dict[int, Table] = {1: Table.COIL, 2: Table.DISCRETE, 3: Table.HOLDING, 4: Table.INPUT}
WRITES: dict[int, Table] = {5: Table.COIL, 6: Table.HOLDING, 15: Table.COIL, 16: Table.HOLDING}
TABLES: dict[int, Table] = {**READS, **WRITES}
# the largest quantity one request of each function may ask for
MAX_QUANTITY: dict[int, int] = {1: MAX_BITS, 2: MAX_BITS, 3: MAX_REGISTERS, 4: MAX_REGISTERS,
                                15: MAX_WRITE_BITS, 16: MAX_WRITE_REGISTERS}


def request_length(head: bytes) -> int | None:
    """Length of the request that starts with ``head``; None if not known (yet)."""
    if len(head) < 2 or head[1] not in FUNCTIONS:
        return None
    return FUNCTIONS[head[1]].request.of(head)


def reply_length(head: bytes) -> int | None:
    """Length of the reply (normal or exception) that starts with ``head`` (the bytes
    from its start on: most replies need 3, a device identification its objects')."""
    if len(head) < 2:
        return None
    if head[1] & 0x80:
        return EXCEPTION_LENGTH
    if head[1] == 43 and len(head) > 2 and head[2] == 0x0E:
        return _device_id_length(head)
    fn = FUNCTIONS.get(head[1])
    return fn.reply.of(head) if fn else None


def _device_id_length(head: bytes) -> int | None:
    """A read device identification reply: 8 header bytes (unit, 2B, 0E, code,
    conformity, more follows, next object, count), then each object's id, length and
    bytes, then the CRC; None until the bytes that say are in."""
    if len(head) < 8:
        return None
    at = 8
    for _ in range(head[7]):
        if len(head) < at + 2:
            return None
        at += 2 + head[at + 1]
    return at + 2


def answer_length(request: bytes) -> int | None:
    """Length of the normal reply to ``request`` (a complete request frame); None where
    the reply's own bytes say (report server id, device identification, ...)."""
    fc = request[1]
    if fc in READ_FUNCTIONS:
        return 5 + data_bytes(fc, int.from_bytes(request[4:6], "big"))
    fn = FUNCTIONS.get(fc)
    return fn.reply.fixed or None if fn else None


def echoed_by_design(request: bytes) -> bool:
    """Whether the normal reply to ``request`` is the request itself, byte for byte (a
    write of one coil or register; diagnostics' return query data): an adapter's echo
    and the device's answer then look the same."""
    return request[1] in (5, 6) or (request[1] == 8 and request[2:4] == b"\x00\x00")


def data_bytes(function: int, count: int) -> int:
    """Data bytes a read of ``count`` registers (3, 4) or bits (1, 2) returns."""
    return (count + 7) // 8 if function in (1, 2) else 2 * count


def read_frame_sizes(count: int, *, coils: bool = False) -> tuple[int, int]:
    """Request and normal response sizes (bytes, CRC included) of one read."""
    return 8, 5 + data_bytes(1 if coils else 3, count)


# where a write request's data begins: FC06 value at 4, FC16 values after the byte count
WRITE_DATA_AT = {5: 4, 6: 4, 15: 7, 16: 7}


def words(data: bytes) -> tuple[int, ...]:
    """Big-endian 16-bit registers; an odd last byte is left out."""
    return tuple(struct.unpack(f">{len(data) // 2}H", data[: len(data) // 2 * 2]))


def bits(data: bytes, count: int) -> tuple[int, ...]:
    """The first ``count`` bits (as many as ``data`` holds), least significant bit first."""
    return tuple([(data[i // 8] >> (i % 8)) & 1 for i in range(min(count, 8 * len(data)))])


def pack_bits(values: Sequence[int]) -> bytes:
    """Bits (any true value is 1) packed least significant bit first, as coils travel."""
    packed = bytearray(data_bytes(1, len(values)))
    for i, bit in enumerate(values):
        if bit:
            packed[i // 8] |= 1 << (i % 8)
    return bytes(packed)
