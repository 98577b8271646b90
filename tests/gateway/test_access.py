"""The gateway's access rules: line settings, writes refused, allowed networks
(rtupoll.gateway.access)."""

from __future__ import annotations

from rtupoll.config.gateway_settings import ServeConfig, serve_config
from rtupoll.config.library import load_one
from rtupoll.gateway.access import Access, line_settings
from rtupoll.gateway.pdu import parse


def test_line_settings_are_address_and_baud_rate_registers() -> None:
    assert {f.name for f in line_settings(load_one("radar-level"))} == \
        {"slave_address", "baud_rate"}
    assert {f.name for f in line_settings(load_one("huiwen-aq"))} == {"slave_address"}
    # one rule with MQTT's: an address register the profile does not readdress through
    # is still the device's address
    assert {f.name for f in line_settings(load_one("eastron-sdm630"))} == {"modbus_address"}
    assert {f.name for f in line_settings(load_one("net-irnet-pro"))} == \
        {"slave_address", "uart_speed"}


def test_access_rules() -> None:
    radar = load_one("radar-level")
    write_addr = parse(bytes.fromhex("06 03 f4 00 07"))  # radar's slave address register
    write_baud = parse(bytes.fromhex("10 03 f5 00 02 04 00 00 00 60"))  # overlaps 0x03F6
    write_other = parse(bytes.fromhex("06 00 20 00 01"))
    read = parse(bytes.fromhex("03 03 f4 00 01"))
    rules = Access(ServeConfig("127.0.0.1", 0), {4: radar})
    assert rules.check(4, read) is None and rules.check(4, write_other) is None
    for ask in (write_addr, write_baud):
        refusal = rules.check(4, ask)
        assert refusal is not None and refusal.code == 1
    assert rules.check(5, write_addr) is None  # unit 5 is not a known radar
    b = rules.check(0, write_other)
    assert b is not None and b.code == 0x0A and "broadcast" in b.reason
    allowed = Access(ServeConfig("127.0.0.1", 0, setup_writes=frozenset({4}), broadcast=True),
                     {4: radar})
    assert allowed.check(4, write_addr) is None and allowed.check(0, write_other) is None
    assert allowed.check(0, write_addr) is not None  # a broadcast would set every radar's
    ro = Access(ServeConfig("127.0.0.1", 0, read_only=True), {})
    refusal = ro.check(4, write_other)
    assert refusal is not None and refusal.code == 1 and "read-only" in refusal.reason
    assert ro.check(4, read) is None


def test_allowed_networks() -> None:
    rules = Access(serve_config("5020", allow=["10.1.0.0/16", "::1"]), {})
    assert rules.peer_allowed("10.1.2.3") and rules.peer_allowed("::1")
    assert rules.peer_allowed("::ffff:10.1.9.9")
    assert not rules.peer_allowed("127.0.0.1") and not rules.peer_allowed("10.2.0.1")
    assert Access(serve_config("5020"), {}).peer_allowed("192.0.2.7")
