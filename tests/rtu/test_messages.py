"""rtu.messages: typed requests and replies, parsed from and encoded to frames."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rtupoll.rtu.crc import with_crc
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.frames import Direction, frame_at
from rtupoll.rtu.functions import FUNCTIONS, MAX_QUANTITY, Table, data_bytes
from rtupoll.rtu.messages import (
    ExceptionReply,
    Malformed,
    OtherReply,
    OtherRequest,
    ReadReply,
    ReadRequest,
    Request,
    WriteMultiple,
    WriteReply,
    WriteSingle,
    parse_reply,
    parse_request,
)

units = st.integers(0, 255)
# built once (a strategy built inside a draw is built and checked again every time)
CODES = st.sampled_from(sorted(FUNCTIONS))
QUANTITIES = {fc: st.integers(1, MAX_QUANTITY[fc]) for fc in (1, 2, 3, 4, 15, 16)}
U16 = st.integers(0, 0xFFFF)


def bits_or_words(draw: st.DrawFn, fc: int, n: int) -> tuple[int, ...]:
    """``n`` coil or input states (FC 1, 2, 5, 15) or registers, drawn as one run of bytes
    (a draw per value was most of the fuzzers' time)."""
    if fc in (1, 2, 5, 15):
        return tuple(b & 1 for b in draw(st.binary(min_size=n, max_size=n)))
    return struct.unpack(f">{n}H", draw(st.binary(min_size=2 * n, max_size=2 * n)))


@st.composite
def requests(draw: st.DrawFn) -> Request:
    unit, fc = draw(units), draw(CODES)
    if fc in (1, 2, 3, 4):
        n = draw(QUANTITIES[fc])
        return ReadRequest(unit, fc, draw(st.integers(0, 0x10000 - n)), n)
    if fc in (5, 6):
        return WriteSingle(unit, fc, draw(U16), bits_or_words(draw, fc, 1)[0])
    if fc in (15, 16):
        n = draw(QUANTITIES[fc])
        values = bits_or_words(draw, fc, n)
        return WriteMultiple(unit, fc, draw(st.integers(0, 0x10000 - n)), values)
    head = with_crc(bytes((unit, fc)) + b"\x00" * 9)  # room for any count byte
    size = FUNCTIONS[fc].request.of(head[:11])
    assert size is not None
    data = draw(st.binary(min_size=size - 4, max_size=size - 4))
    if FUNCTIONS[fc].request.count_at:  # the count byte says how much follows
        at = FUNCTIONS[fc].request.count_at - 2
        extra = draw(st.binary(max_size=20))
        data = data[:at] + bytes((len(extra),)) + extra
    return OtherRequest(unit, fc, data)


@given(requests())
def test_every_request_parses_back_from_its_frame_and_its_pdu(req: Request) -> None:
    assert parse_request(req.frame()) == req
    assert parse_request(req.pdu(), unit=req.unit) == req
    assert frame_at(req.frame(), direction=Direction.REQUEST) == len(req.frame())


@given(requests(), st.data())
def test_every_reply_parses_back(req: Request, data: st.DataObject) -> None:
    code = data.draw(st.integers(0, 255))
    exc = ExceptionReply(req.unit, req.function, code)
    assert parse_reply(req, exc.frame()) == exc
    if isinstance(req, ReadRequest):
        values = bits_or_words(data.draw, req.function, req.count)
        normal: ReadReply | WriteReply | OtherReply = ReadReply(req.unit, req.function, values)
        assert len(normal.pdu()) == 2 + data_bytes(req.function, req.count)
    elif isinstance(req, WriteSingle):
        normal = WriteReply(req.unit, req.function, req.address, req.value)
        assert normal.frame() == req.frame()  # the echo
    elif isinstance(req, WriteMultiple):
        normal = WriteReply(req.unit, req.function, req.address, req.count)
    else:
        return
    assert parse_reply(req, normal.frame()) == normal
    assert parse_reply(req, normal.pdu(), unit=req.unit) == normal
    answering = frame_at(normal.frame(), direction=Direction.REPLY, answering=req.frame())
    assert answering == len(normal.frame())


@settings(max_examples=max(300, settings().max_examples))
@given(st.binary(max_size=300), st.one_of(st.none(), units))
def test_any_bytes_parse_or_are_refused_with_a_reason(data: bytes, unit: int | None) -> None:
    try:
        req = parse_request(data, unit=unit)
    except Malformed as bad:
        assert bad.reason and bad.code in (None, ExceptionCode.ILLEGAL_FUNCTION,
                                           ExceptionCode.ILLEGAL_ADDRESS,
                                           ExceptionCode.ILLEGAL_VALUE)
    else:  # what parses encodes back to the same message
        assert parse_request(req.frame()) == req


@settings(max_examples=max(300, settings().max_examples))
@given(requests(), st.binary(max_size=300), st.booleans())
def test_any_bytes_answer_a_request_or_are_refused(req: Request, data: bytes,
                                                   framed: bool) -> None:
    try:
        reply = parse_reply(req, with_crc(bytes((req.unit,)) + data) if framed else data,
                            unit=None if framed else req.unit)
    except Malformed as bad:
        assert bad.reason and bad.code is None  # a master answers nothing
    else:
        assert reply.unit == req.unit and reply.function == req.function
        assert parse_reply(req, reply.frame()) == reply


def test_the_messages_encode_their_own_frames() -> None:
    assert ReadRequest(1, 3, 0x10, 2).frame() == bytes.fromhex("01 03 00 10 00 02 C5 CE")
    assert WriteSingle(1, 6, 7, 0xBEEF).frame() == bytes.fromhex("01 06 00 07 BE EF 08 27")
    assert WriteMultiple(1, 16, 7, (1, 2)).frame() == \
        bytes.fromhex("01 10 00 07 00 02 04 00 01 00 02 62 48")
    assert parse_request(bytes.fromhex("0F 00 13 00 0A 02 CD 01"), unit=0x11) == \
        WriteMultiple(0x11, 15, 0x13, (1, 0, 1, 1, 0, 0, 1, 1, 1, 0))  # the standard's


@pytest.mark.parametrize(("pdu", "code", "words"), [
    (b"", ExceptionCode.ILLEGAL_FUNCTION, "empty PDU"),
    (b"\x83\x00\x00\x00\x01", ExceptionCode.ILLEGAL_FUNCTION, "function 131"),
    (b"\x63\x00", ExceptionCode.ILLEGAL_FUNCTION, "function 99"),
    (b"\x03\x00\x00\x00", ExceptionCode.ILLEGAL_VALUE, "4 bytes, the function takes 5"),
    (b"\x03\x00\x00\x00\x00", ExceptionCode.ILLEGAL_VALUE, "quantity 0 is outside 1..125"),
    (b"\x03\x00\x00\x00\x7E", ExceptionCode.ILLEGAL_VALUE, "quantity 126 is outside 1..125"),
    (b"\x01\x00\x00\x07\xD1", ExceptionCode.ILLEGAL_VALUE, "quantity 2001 is outside 1..2000"),
    (b"\x04\xFF\xFF\x00\x02", ExceptionCode.ILLEGAL_ADDRESS, "runs past 0xFFFF"),
    (b"\x05\x00\x01\x12\x34", ExceptionCode.ILLEGAL_VALUE, "neither ON nor OFF"),
    (b"\x10\x00\x01\x00\x02\x02\x00\x01", ExceptionCode.ILLEGAL_VALUE, "byte count 2 does not fit"),
    (b"\x10\x00\x01\x00\x7C\x00", ExceptionCode.ILLEGAL_VALUE, "quantity 124 is outside 1..123"),
    (b"\x0F\x00\x01\x00\x03\x00", ExceptionCode.ILLEGAL_VALUE,
     "byte count 0 does not fit quantity 3"),
])
def test_a_refused_request_says_why_and_which_code(pdu: bytes, code: int, words: str) -> None:
    with pytest.raises(Malformed, match=words) as got:
        parse_request(pdu, unit=1)
    assert got.value.code == code


def test_a_frame_is_refused_for_its_crc_with_no_code() -> None:
    frame = bytearray(ReadRequest(1, 4, 0, 1).frame())
    frame[-1] ^= 1
    with pytest.raises(Malformed, match="CRC error") as got:
        parse_request(bytes(frame))
    assert got.value.code is None and got.value.unit == 1


@pytest.mark.parametrize(("reply", "words"), [
    (b"\x02\x04\x02\x00\x01", "unit 2 answers a request to unit 1"),
    (b"\x01\x03\x02\x00\x01", "function 3 does not answer function 4"),
    (b"\x01\x04\x04\x00\x01\x00\x02", "carries 2 data bytes, this has 4"),
    (b"\x01\x84\x02\x00", "an exception reply is 2 PDU bytes, this is 3"),
])
def test_a_reply_that_does_not_answer_is_refused(reply: bytes, words: str) -> None:
    with pytest.raises(Malformed, match=words):
        parse_reply(ReadRequest(1, 4, 0, 1), with_crc(reply))


def test_a_write_reply_must_be_its_confirmation() -> None:
    req = WriteSingle(1, 6, 7, 42)
    with pytest.raises(Malformed, match="not the confirmation"):
        parse_reply(req, WriteSingle(1, 6, 7, 43).frame())
    short = with_crc(bytes.fromhex("01 06 02 00 2A"))  # laid out like a read reply
    with pytest.raises(Malformed, match="not the confirmation"):
        parse_reply(req, short)


def test_the_sniffer_shows_a_malformed_request_and_gives_it_no_registers() -> None:
    from rtupoll.rtu.stream import Seen, Transaction, WireFrame
    from rtupoll.sniff.model import describe

    def sniffed(frame: bytes) -> Seen | None:
        return Transaction("timeout", 0.0, WireFrame(frame, 0.0, 0.0)).asked

    bad = with_crc(bytes.fromhex("07 03 00 10 00 C8"))  # a read of 200 registers
    req = sniffed(bad)
    assert isinstance(req, Malformed) and req.unit == 7
    assert describe(req) == \
        "fc03 function 0x03: read holding registers: quantity 200 is outside 1..125"
    good = sniffed(ReadRequest(7, 3, 0x10, 2).frame())
    assert good == ReadRequest(7, 3, 0x10, 2) and good.table is Table.HOLDING
    assert describe(good) == "fc03 read holding 0x0010 x2"
    assert describe(sniffed(WriteSingle(7, 6, 0x9C41, 3).frame())) == \
        "fc06 write holding 0x9C41 x1"


def test_the_gateway_and_the_simulator_answer_the_parsers_code() -> None:
    from rtupoll.config.library import load_one
    from rtupoll.gateway.pdu import BadRequest, parse
    from rtupoll.sim.device import SimDevice, SimDeviceConfig
    from rtupoll.sim.engine import Engine

    pdu = bytes.fromhex("04 FF FF 00 02")  # runs past 0xFFFF
    with pytest.raises(BadRequest) as got:
        parse(pdu)
    assert got.value.code == ExceptionCode.ILLEGAL_ADDRESS
    engine = Engine([SimDeviceConfig(load_one("huiwen-aq"), 3)], tick=None)
    [reply] = engine.handle(with_crc(b"\x03" + pdu))
    assert reply.data == ExceptionReply(3, 4, ExceptionCode.ILLEGAL_ADDRESS).frame()
    device: SimDevice = engine.device(3)
    answer = device.handle(ReadRequest(3, 4, 30009, 1))
    assert answer is not None and isinstance(parse_reply(ReadRequest(3, 4, 30009, 1), answer),
                                             ReadReply)


def test_guess_reads_up_to_the_read_limit() -> None:
    from rtupoll.cli.guess import _spec
    from rtupoll.errors import UsageError

    assert _spec("input:0:125") == (Table.INPUT, 0, MAX_QUANTITY[4])
    with pytest.raises(UsageError, match=r"COUNT 126 is outside 1\.\.125 registers"):
        _spec("input:0:126")
