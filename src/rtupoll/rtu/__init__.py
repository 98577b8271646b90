"""Modbus RTU as bytes and rules, sans-IO: no serial port, no asyncio, no clock of its own.

In the spirit of h11: everything here is a pure function of the bytes and times it
is given, so every rule is tested in virtual time and reused by the bus (a thin I/O
adapter), the simulator's engine, ``decode`` and the sniffer.

- ``functions``: the function table (request and reply lengths per function code,
  names);
- ``exception_codes``: ``ExceptionCode``, the exception codes by name;
- ``crc``: the CRC-16;
- ``timing``: character timing and the 3.5-character silence;
- ``match``: which bytes answer a request, and why an unanswered attempt failed;
- ``line``: the master's line discipline (when a frame may go, drains, late replies);
- ``stream``: a listen-only tap's bytes split into frames and transactions (sniffing);
- ``capture``: captured byte streams split into frames and decoded;
- ``messages``: typed requests and replies (each encodes itself), one strict parser for
  each: the one set of message types for master, gateway, simulator and sniffer;
- ``frames``: where a frame ends (``frame_at``), for every reader of bytes.
"""

from rtupoll.rtu.crc import crc16, crc_ok, with_crc
from rtupoll.rtu.exception_codes import EXCEPTION_NAMES, ExceptionCode, exception_name
from rtupoll.rtu.functions import (
    FUNCTION_NAMES,
    FUNCTIONS,
    Table,
    read_frame_sizes,
)
from rtupoll.rtu.timing import Framing, transaction_wire_time

__all__ = [
    "EXCEPTION_NAMES", "FUNCTIONS", "FUNCTION_NAMES", "ExceptionCode", "Framing", "Table",
    "crc16", "crc_ok",
    "exception_name", "read_frame_sizes", "transaction_wire_time", "with_crc",
]
