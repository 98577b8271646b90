"""Where a frame ends in a stream of bytes: its length, NEED_MORE or NOT_A_FRAME
(rtupoll.rtu.frames)."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from rtupoll.rtu.frames import NEED_MORE, NOT_A_FRAME, Direction, frame_at, lengths
from rtupoll.rtu.messages import ReadReply, ReadRequest, WriteMultiple


@settings(max_examples=max(300, settings().max_examples))
@given(st.binary(max_size=300), st.sampled_from(Direction), st.booleans())
def test_frame_at_says_length_need_more_or_not_a_frame(data: bytes, direction: Direction,
                                                        final: bool) -> None:
    n = frame_at(data, direction=direction, final=final)
    assert n in (NEED_MORE, NOT_A_FRAME) or 4 <= n <= len(data)
    if final:
        assert n != NEED_MORE
    if n == NEED_MORE:
        assert max(lengths(data[:11], direction)) > len(data)


def test_frame_at_waits_for_the_likelier_length_and_takes_the_expected_one() -> None:
    req = WriteMultiple(1, 16, 0, (1, 2, 3)).frame()
    assert frame_at(req[:5], direction=Direction.REQUEST) == NEED_MORE  # no count byte yet
    assert frame_at(req[:-1], direction=Direction.REQUEST) == NEED_MORE
    assert frame_at(req[:-1], direction=Direction.REQUEST, final=True) == NOT_A_FRAME
    assert frame_at(b"\xff" + req, 1, direction=Direction.REQUEST) == len(req)
    assert frame_at(req, direction=Direction.REPLY) == NOT_A_FRAME  # not 8 bytes of echo
    assert frame_at(b"\x01\x63\x00\x00", direction=Direction.REQUEST) == NOT_A_FRAME
    reply = ReadReply(1, 4, (5,)).frame()
    read = ReadRequest(1, 4, 0, 1).frame()
    assert frame_at(reply + read, direction=Direction.REPLY, answering=read) == len(reply)
    assert lengths(read[:11], Direction.EITHER) == (8, 5 + read[2])
