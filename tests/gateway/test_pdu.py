"""The gateway's PDU checks: what it understands, what it refuses with which exception
code, the replies it sends (rtupoll.gateway.pdu)."""

from __future__ import annotations

import pytest

from rtupoll.gateway.pdu import BadRequest, parse
from rtupoll.rtu import Table
from rtupoll.rtu.messages import ReadReply, WriteMultiple, WriteReply, WriteSingle

READ = bytes.fromhex("04 75 36 00 05")  # Huiwen: 5 input registers at 30006


def test_parse_understands_reads_and_writes() -> None:
    a = parse(READ)
    assert (a.function, a.table, a.address, a.count, a.read, a.write) == \
        (4, Table.INPUT, 0x7536, 5, True, False)
    w = parse(bytes.fromhex("10 00 10 00 02 04 00 01 00 02"))
    assert (w.table, w.address, w.count, w.write) == (Table.HOLDING, 0x10, 2, True)
    assert w.message == WriteMultiple(0, 16, 0x10, (1, 2))
    c = parse(bytes.fromhex("0f 00 00 00 0a 02 05 02"), unit=7)
    assert c.message == WriteMultiple(7, 15, 0, (1, 0, 1, 0, 0, 0, 0, 0, 0, 1))
    assert parse(bytes.fromhex("05 00 d0 ff 00")).message == WriteSingle(0, 5, 0xD0, 1)
    other = parse(bytes.fromhex("08 00 00 12 34"))
    assert (other.table, other.address, other.count, other.read) == (None, 0, 0, False)


@pytest.mark.parametrize(("pdu", "code"), [
    (bytes.fromhex("03 00 00 00 7e"), 3),  # 126 registers
    (bytes.fromhex("03 00 00 00 00"), 3),
    (bytes.fromhex("03 ff ff 00 02"), 2),  # runs past 0xFFFF
    (bytes.fromhex("05 00 d0 12 34"), 3),  # a coil value neither ON nor OFF
    (bytes.fromhex("10 00 10 00 02 03 00 01 00"), 3),  # byte count does not fit
    (bytes.fromhex("41 00"), 1),  # not a Modbus function
    (bytes.fromhex("83 00"), 1),
])
def test_parse_refuses_with_the_servers_exception_code(pdu: bytes, code: int) -> None:
    with pytest.raises(BadRequest) as err:
        parse(pdu)
    assert err.value.code == code


def test_replies_are_the_messages_own_pdus() -> None:
    assert ReadReply(1, 3, (555, 0, 100)).pdu() == bytes.fromhex("03 06 02 2b 00 00 00 64")
    assert ReadReply(1, 1, (1, 0, 1, 1, 0, 0, 0, 0, 1)).pdu() == bytes.fromhex("01 02 0d 01")
    assert WriteReply(1, 6, 0x9C41, 5).pdu() == bytes.fromhex("06 9c 41 00 05")
    assert WriteReply(1, 16, 0x10, 2).pdu() == bytes.fromhex("10 00 10 00 02")
