"""A port's name (``rtupoll.io.port_names``): a gateway's ``tcp://HOST:PORT``, the path
behind ``nodtr://`` and ``rtupoll://N`` URLs, and the URL pyserial is given."""

from __future__ import annotations

import pytest

from rtupoll.errors import UsageError
from rtupoll.io import port_names


def test_port_url_asks_for_nodtr_only_on_a_device() -> None:
    assert port_names.port_url("/dev/ttyUSB3", deassert_dtr=True) == "nodtr:///dev/ttyUSB3"
    assert port_names.port_url("socket://h:1", deassert_dtr=True) == "socket://h:1"
    assert port_names.port_url("/dev/ttyUSB3", deassert_dtr=False) == "/dev/ttyUSB3"


@pytest.mark.parametrize(("port", "path"), [
    ("/dev/ttyUSB0", "/dev/ttyUSB0"),
    ("nodtr:///dev/ttyUSB0", "/dev/ttyUSB0"),
    ("NODTR:///dev/ttyUSB0", "/dev/ttyUSB0"),
    ("rtupoll://12//dev/ttyUSB0", "/dev/ttyUSB0"),  # as claim spells it: N, then the path
    ("rtupoll://3/COM3", "COM3"),
])
def test_device_path_is_the_path_behind_the_url(port: str, path: str) -> None:
    assert port_names.device_path(port) == path


def test_a_gateway_is_tcp_host_port() -> None:
    assert port_names.gateway("tcp://192.168.1.20:502") == ("192.168.1.20", 502)
    assert port_names.gateway("TCP://[::1]:4001/") == ("::1", 4001)
    assert port_names.gateway("/dev/ttyUSB0") is None
    assert port_names.gateway("socket://h:1") is None


@pytest.mark.parametrize("port", ["tcp://host", "tcp://:502", "tcp://h:0", "tcp://h:65536",
                                  "tcp://h:x"])
def test_a_gateway_without_host_or_port_is_one_line(port: str) -> None:
    with pytest.raises(UsageError, match="expected tcp://HOST:PORT"):
        port_names.gateway(port)
