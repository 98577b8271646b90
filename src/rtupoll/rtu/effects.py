"""What a request does to a device: every function code 0-255 by its effect, and the
registers and coils a request touches, pure.

The one table every access decision is made from (the gateway's guard, its read-only
mode and broadcasts, the write paths): lengths and names stay in ``functions``; this
module says only what a request *does*.

- ``READ``: reads, changes nothing (the four data tables, and device information:
  exception status, event counter and log, server id, FIFO queue (which the standard
  says it does not clear), device identification, the diagnostics that return data);
- ``WRITE``: changes registers or coils (5, 6, 15, 16, 22, 23; file records, 21);
- ``STATE``: a diagnostic that changes the device's state although it writes no
  register: restart communications (clears the event log, leaves listen-only mode),
  force listen only (a compliant device stops answering until it is restarted or power
  cycled), change the ASCII delimiter, clear the counters, clear the overrun counter;
- ``UNKNOWN``: everything else: reserved and user-defined codes, the legacy programming
  functions (9, 10, 13, 14), encapsulated transports other than device identification,
  exception codes (128-255) sent as requests, unassigned diagnostic sub-functions.

An access rule passes a request only when it knows it is harmless: whatever is unknown
or changes state is refused unless a rule allows it.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from rtupoll.rtu.functions import READS, Table

MIN_UNIT, MAX_UNIT = 1, 247  # addressable devices; 0 is broadcast
RESERVED_UNITS = range(248, 256)  # reserved by Modbus RTU; 0xFE is "whoever is there"


class Effect(str, enum.Enum):
    READ = "read"
    WRITE = "write"
    STATE = "state-changing diagnostic"
    UNKNOWN = "unknown"


# function code -> effect; a code not listed is UNKNOWN. FC 8 and 43 depend on the
# sub-function (MEI type): DIAGNOSTICS and MEI below.
FUNCTION_EFFECTS: dict[int, Effect] = {
    1: Effect.READ, 2: Effect.READ, 3: Effect.READ, 4: Effect.READ,
    5: Effect.WRITE, 6: Effect.WRITE,
    7: Effect.READ,  # read exception status
    11: Effect.READ, 12: Effect.READ,  # comm event counter, comm event log
    15: Effect.WRITE, 16: Effect.WRITE,
    17: Effect.READ,  # report server id
    20: Effect.READ, 21: Effect.WRITE,  # read / write file record
    22: Effect.WRITE,  # mask write register
    23: Effect.WRITE,  # read/write multiple registers: writes, then reads
    24: Effect.READ,  # read FIFO queue (the standard: "does not clear them")
}

DIAGNOSTICS: dict[int, Effect] = {  # FC 8 sub-function -> effect
    0x00: Effect.READ,  # return query data (an echo)
    0x01: Effect.STATE,  # restart communications option (clears the event log)
    0x02: Effect.READ,  # return diagnostic register
    0x03: Effect.STATE,  # change ASCII input delimiter
    0x04: Effect.STATE,  # force listen only mode: silent until restarted
    0x0A: Effect.STATE,  # clear counters and diagnostic register
    **{sub: Effect.READ for sub in range(0x0B, 0x13)},  # return a counter (11-18)
    0x14: Effect.STATE,  # clear overrun counter and flag
}

MEI: dict[int, Effect] = {0x0E: Effect.READ}  # FC 43: read device identification
# (0x0D, CANopen general reference, carries any CANopen request: UNKNOWN)

# what a broadcast (unit 0) may carry: a write with no reply; FC 23 carries a read
BROADCAST_FUNCTIONS = frozenset({5, 6, 15, 16, 22})
# reads a read-only gateway passes: the four data tables only (device information,
# diagnostics and encapsulated transports are each device's own; see docs/gateway.md)
TABLE_READS = frozenset(READS)


def effect(pdu: bytes) -> Effect:
    """What the request PDU (function code and data) does; UNKNOWN for an FC 8 or 43
    too short to name its sub-function."""
    if not pdu:
        return Effect.UNKNOWN
    fc = pdu[0]
    if fc == 8:
        if len(pdu) < 3:
            return Effect.UNKNOWN
        return DIAGNOSTICS.get(struct.unpack_from(">H", pdu, 1)[0], Effect.UNKNOWN)
    if fc == 43:
        return MEI.get(pdu[1], Effect.UNKNOWN) if len(pdu) >= 2 else Effect.UNKNOWN
    return FUNCTION_EFFECTS.get(fc, Effect.UNKNOWN)


def function_effect(function: int, sub: int | None = None) -> Effect:
    """The effect of a function code (with its FC 8 sub-function or FC 43 MEI type)."""
    if function == 8:
        return Effect.UNKNOWN if sub is None else DIAGNOSTICS.get(sub, Effect.UNKNOWN)
    if function == 43:
        return Effect.UNKNOWN if sub is None else MEI.get(sub, Effect.UNKNOWN)
    return FUNCTION_EFFECTS.get(function, Effect.UNKNOWN)


@dataclass(frozen=True)
class Reach:
    """A run of one table a request reads or writes: ``address`` .. ``address+count-1``."""

    table: Table
    address: int
    count: int
    write: bool

    def overlaps(self, table: Table, lo: int, hi: int) -> bool:
        """Whether it touches any of ``table``'s lo..hi-1."""
        return self.table is table and self.address < hi and lo < self.address + self.count


def reaches(pdu: bytes) -> tuple[Reach, ...] | None:
    """The registers and coils a request PDU reads and writes, or None when they cannot be
    known from the request (a function with no table, such as file records and
    diagnostics, or a request too short to say). A write's runs come first."""
    if not pdu:
        return None
    fc, size = pdu[0], len(pdu)
    if fc in READS and size >= 5:
        address, n = struct.unpack_from(">HH", pdu, 1)
        return (Reach(READS[fc], address, n, False),)
    if fc in (5, 6) and size >= 5:
        return (Reach(Table.COIL if fc == 5 else Table.HOLDING,
                      struct.unpack_from(">H", pdu, 1)[0], 1, True),)
    if fc in (15, 16) and size >= 5:
        address, n = struct.unpack_from(">HH", pdu, 1)
        return (Reach(Table.COIL if fc == 15 else Table.HOLDING, address, n, True),)
    if fc == 22 and size >= 3:  # mask write: one holding register
        return (Reach(Table.HOLDING, struct.unpack_from(">H", pdu, 1)[0], 1, True),)
    if fc == 23 and size >= 9:  # read address, count, write address, count
        ra, rn, wa, wn = struct.unpack_from(">HHHH", pdu, 1)
        return (Reach(Table.HOLDING, wa, wn, True), Reach(Table.HOLDING, ra, rn, False))
    return None


def writes(pdu: bytes) -> tuple[Reach, ...] | None:
    """The runs a request writes (() for one that writes none), None when unknown."""
    got = reaches(pdu)
    if got is None:
        return () if effect(pdu) is not Effect.WRITE else None
    return tuple(r for r in got if r.write)
