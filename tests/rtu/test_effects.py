"""The function-effect table (rtupoll.rtu.effects), checked against rules written here from
the Modbus application protocol: every function code's effect, FC8's sub-functions, the
registers FC22 and FC23 reach."""

from __future__ import annotations

import struct

from rtupoll.rtu import Table
from rtupoll.rtu.effects import DIAGNOSTICS, Effect, effect, function_effect, reaches

# the rules, from the Modbus application protocol, written apart from rtupoll.rtu.effects
HARMLESS_READS = {1, 2, 3, 4, 7, 11, 12, 17, 20, 24}
HARMLESS_DIAGNOSTICS = {0x00, 0x02, *range(0x0B, 0x13)}
STATE_DIAGNOSTICS = {0x01, 0x03, 0x04, 0x0A, 0x14}


def test_every_function_code_has_one_effect_and_fc8_is_decided_by_its_sub_function() -> None:
    table = {fc: function_effect(fc) for fc in range(256)}
    assert {fc for fc, e in table.items() if e is Effect.WRITE} == {5, 6, 15, 16, 21, 22, 23}
    assert {fc for fc, e in table.items() if e is Effect.READ} == HARMLESS_READS
    assert all(table[fc] is Effect.UNKNOWN for fc in range(128, 256))  # exception codes
    assert {s for s, e in DIAGNOSTICS.items() if e is Effect.STATE} == STATE_DIAGNOSTICS
    for sub in range(0x10000):
        want = Effect.STATE if sub in STATE_DIAGNOSTICS else Effect.READ \
            if sub in HARMLESS_DIAGNOSTICS else Effect.UNKNOWN
        assert effect(struct.pack(">BHH", 8, sub, 0)) is want
    assert effect(bytes((43, 0x0E, 1, 0))) is Effect.READ
    assert effect(bytes((43, 0x0D, 1, 0))) is Effect.UNKNOWN
    assert effect(b"") is Effect.UNKNOWN and effect(b"\x08\x00") is Effect.UNKNOWN


def test_fc22_and_fc23_reach_the_registers_they_write() -> None:
    mask = struct.pack(">BHHH", 22, 0x9C41, 0, 5)
    rw = struct.pack(">BHHHHBH", 23, 0x0010, 2, 0x9C41, 1, 2, 9)
    assert [(r.table, r.address, r.count, r.write) for r in reaches(mask) or ()] == [
        (Table.HOLDING, 0x9C41, 1, True)]
    assert [(r.address, r.count, r.write) for r in reaches(rw) or ()] == [
        (0x9C41, 1, True), (0x0010, 2, False)]
