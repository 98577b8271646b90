"""Modbus exception codes: one set of names (``rtu.exception_codes.ExceptionCode``),
the wire's ints, and the specification's names for each."""

from __future__ import annotations

from rtupoll.errors import DeviceException
from rtupoll.rtu import EXCEPTION_NAMES, ExceptionCode, exception_name
from rtupoll.rtu.messages import ExceptionReply


def test_every_code_is_the_wire_int_and_has_the_specifications_name() -> None:
    assert [int(c) for c in ExceptionCode] == [1, 2, 3, 4, 5, 6, 7, 8, 10, 11]
    assert set(EXCEPTION_NAMES) == set(ExceptionCode)
    assert exception_name(ExceptionCode.ILLEGAL_ADDRESS) == exception_name(2) \
        == "ILLEGAL DATA ADDRESS"
    assert exception_name(ExceptionCode.TARGET_FAILED) == \
        "GATEWAY TARGET DEVICE FAILED TO RESPOND"
    assert exception_name(9) == "UNKNOWN EXCEPTION"


def test_a_code_goes_on_the_wire_and_into_words_as_its_number() -> None:
    assert ExceptionReply(1, 3, ExceptionCode.ILLEGAL_ADDRESS).frame()[:3] == b"\x01\x83\x02"
    exc = DeviceException(ExceptionCode.ILLEGAL_ADDRESS, unit=7, function=3)
    assert str(exc) == "device 7 answered to function 0x03 with exception 02 ILLEGAL DATA ADDRESS"
    assert exc.code == 2 and f"{exc.code}" == "2"
