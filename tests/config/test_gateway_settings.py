"""The gateway's serve settings: listen forms, a site file's serve section
(rtupoll.config.gateway_settings)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.gateway_settings import parse_listen, serve_config
from rtupoll.config.site import load_site
from rtupoll.errors import ConfigError, UsageError


def test_listen_forms() -> None:
    assert parse_listen("5020") == ("mbap", "127.0.0.1", 5020)
    assert parse_listen("0.0.0.0:502") == ("mbap", "0.0.0.0", 502)
    assert parse_listen("rtu+tcp://[::1]:4001") == ("rtu", "::1", 4001)
    for bad in ("udp://1.2.3.4:5", "host:", "host:70000", "x"):
        with pytest.raises(UsageError):
            parse_listen(bad)
    with pytest.raises(UsageError, match="not a network"):
        serve_config("5020", allow=["10.0.0.0/33"])


def test_site_file_serve_and_a_bus_without_devices(tmp_path: Path) -> None:
    site = tmp_path / "site.yaml"
    site.write_text(
        "buses:\n"
        "  - name: a\n    port: /dev/ttyUSB0\n    baudrate: 9600\n"
        "    serve: 5020\n"
        "  - name: b\n    port: /dev/ttyUSB1\n"
        "    serve:\n      listen: rtu+tcp://0.0.0.0:4001\n      allow: [10.0.0.0/8]\n"
        "      read_only: true\n      cache: 2\n      setup_writes: [4]\n"
        "      client_queue: 2\n      max_clients: 5\n      max_per_address: 1\n"
        "    devices:\n      - {profile: radar-level, address: 4}\n")
    a, b = load_site(site).buses
    assert a.devices == () and a.serve is not None and (a.serve.host, a.serve.port) == \
        ("127.0.0.1", 5020)
    assert b.serve is not None and b.serve.framing == "rtu" and b.serve.read_only
    assert b.serve.cache == 2 and b.serve.setup_writes == {4} and len(b.serve.allow) == 1
    assert (b.serve.client_queue, b.serve.max_clients, b.serve.max_per_address) == (2, 5, 1)
    assert (a.serve.client_queue, a.serve.max_clients, a.serve.max_per_address) == (4, 32, 8)
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n    serve: {listen: 5020, max_clients: 0}\n")
    with pytest.raises(ConfigError, match=r"site.yaml:3: .*0"):
        load_site(site)
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n    serve: {listen: 5020, cahce: 2}\n")
    with pytest.raises(ConfigError, match=r"site.yaml:3: .*cahce.*did you mean 'cache'"):
        load_site(site)
    site.write_text("buses:\n  - port: /dev/ttyUSB0\n")
    with pytest.raises(ConfigError, match="devices"):
        load_site(site)
