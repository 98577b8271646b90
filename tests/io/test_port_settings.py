"""One bus's port and line settings (``rtupoll.io.port_settings``): the framing the line's
timing follows and the gateway a ``tcp://`` port names."""

from __future__ import annotations

from rtupoll.io.port_settings import PortSettings, Rs485
from rtupoll.rtu import Framing


def test_settings_give_the_lines_framing_and_gateway() -> None:
    s = PortSettings("tcp://gw:4001", baudrate=19200, parity="E", rs485=Rs485(0.001))
    assert s.framing == Framing(19200, 8, "E", 1)
    assert s.gateway == ("gw", 4001)
    assert PortSettings("/dev/ttyUSB0").gateway is None
    assert s.rs485 == Rs485(before=0.001, after=0.0)
