"""rtu/capture.py: decode through the one strict parser (rtu/messages.py)."""

from __future__ import annotations

from rtupoll.rtu import Table, with_crc
from rtupoll.rtu.capture import decode_frame, decode_stream
from rtupoll.rtu.messages import (
    ExceptionReply,
    ReadReply,
    ReadRequest,
    WriteMultiple,
    WriteReply,
)

REQ = ReadRequest(3, 4, 0x7536, 2)
REPLY = ReadReply(3, 4, (25, 50))


def test_a_request_and_its_reply_are_decoded_as_their_messages() -> None:
    req, reply = decode_stream([REQ.frame() + REPLY.frame()])
    assert (req.kind, req.message, req.table, req.start, req.count) == \
        ("request", REQ, Table.INPUT, 0x7536, 2)
    assert (reply.kind, reply.message, reply.start, reply.values) == \
        ("response", REPLY, 0x7536, (25, 50))
    write = WriteMultiple(3, 16, 0x10, (1, 2))
    w, echo = decode_stream([write.frame(), WriteReply(3, 16, 0x10, 2).frame()])
    assert w.message == write and w.values == (1, 2)
    assert echo.message == WriteReply(3, 16, 0x10, 2)
    _, refused = decode_stream([REQ.frame(), ExceptionReply(3, 4, 2).frame()])
    assert refused.message == ExceptionReply(3, 4, 2) and refused.exception == 2


def test_a_bad_crc_is_shown_and_the_frame_still_decoded_from_its_message() -> None:
    bad = REPLY.frame()[:-1] + bytes([REPLY.frame()[-1] ^ 1])
    [req] = decode_stream([REQ.frame()])
    reply = decode_frame(bad, None, req)  # (as the splitter hands it over)
    assert not reply.crc_ok and reply.crc_expected == REPLY.frame()[-2:]
    assert reply.message == REPLY and reply.values == (25, 50)
    assert any("CRC" in n and "wrong" in n for n in reply.notes)


def test_what_the_parser_refuses_is_laid_out_with_its_reason() -> None:
    [req] = decode_stream([with_crc(bytes.fromhex("07 03 00 10 00 C8"))])  # 200 registers
    assert req.message is None and (req.start, req.count) == (0x10, 200)
    assert "read holding registers: quantity 200 is outside 1..125" in req.notes
    short = ReadReply(3, 4, (25,)).frame()  # one register for a read of two
    _, reply = decode_stream([REQ.frame(), short])
    assert reply.message is None and reply.values == (25,)
    assert "the request asked for 2, which is 4 bytes" in reply.notes
