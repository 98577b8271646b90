"""Modbus exception codes: the one set of names for the byte after ``function | 0x80``.

An ``IntEnum``: a code is the int on the wire, compared, packed and formatted as one
(``f"{code:02d}"`` is ``02``); ``EXCEPTION_NAMES`` has the specification's name of
each (``exception_name``). The master, the gateway, the simulator and the sniffer all
name codes from here, never by number.
"""

from __future__ import annotations

import enum


class ExceptionCode(enum.IntEnum):
    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_ADDRESS = 0x02  # illegal data address: a register the device does not have
    ILLEGAL_VALUE = 0x03  # illegal data value: a count, a value or a request it refuses
    DEVICE_FAILURE = 0x04
    ACKNOWLEDGE = 0x05
    DEVICE_BUSY = 0x06
    NEGATIVE_ACKNOWLEDGE = 0x07
    MEMORY_PARITY_ERROR = 0x08
    PATH_UNAVAILABLE = 0x0A  # a gateway's: no path to the unit (queue full, port gone)
    TARGET_FAILED = 0x0B  # a gateway's: the unit did not answer


EXCEPTION_NAMES: dict[int, str] = {
    ExceptionCode.ILLEGAL_FUNCTION: "ILLEGAL FUNCTION",
    ExceptionCode.ILLEGAL_ADDRESS: "ILLEGAL DATA ADDRESS",
    ExceptionCode.ILLEGAL_VALUE: "ILLEGAL DATA VALUE",
    ExceptionCode.DEVICE_FAILURE: "SERVER DEVICE FAILURE",
    ExceptionCode.ACKNOWLEDGE: "ACKNOWLEDGE",
    ExceptionCode.DEVICE_BUSY: "SERVER DEVICE BUSY",
    ExceptionCode.NEGATIVE_ACKNOWLEDGE: "NEGATIVE ACKNOWLEDGE",
    ExceptionCode.MEMORY_PARITY_ERROR: "MEMORY PARITY ERROR",
    ExceptionCode.PATH_UNAVAILABLE: "GATEWAY PATH UNAVAILABLE",
    ExceptionCode.TARGET_FAILED: "GATEWAY TARGET DEVICE FAILED TO RESPOND",
}


def exception_name(code: int) -> str:
    """``ILLEGAL DATA ADDRESS`` for 2; ``UNKNOWN EXCEPTION`` for a code the standard lacks."""
    return EXCEPTION_NAMES.get(code, "UNKNOWN EXCEPTION")
