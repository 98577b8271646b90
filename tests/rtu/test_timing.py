"""Framing's wire times: the inter-frame silence, a transaction's time on the wire
(rtupoll.rtu.timing)."""

from __future__ import annotations

import pytest

from rtupoll.rtu import Framing, transaction_wire_time


def test_inter_frame_silence() -> None:
    assert Framing(9600).silence == pytest.approx(3.5 * 10 / 9600)
    assert Framing(115200).silence == 0.00175  # fixed above 19200 baud
    assert Framing(9600, parity="E").bits_per_char == 11


def test_transaction_wire_time_at_9600() -> None:
    # 8-byte request, 9-byte reply, two silences: 17.7 ms + 7.3 ms
    assert transaction_wire_time(Framing(9600), 8, 9) == pytest.approx(0.02500, abs=1e-4)
