"""The gateway's pure parts: MBAP and RTU-over-TCP framing, PDU checks, access rules,
the read cache and the serve settings (rtupoll.gateway)."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from rtupoll.config.gateway_settings import ServeConfig, parse_listen, serve_config
from rtupoll.config.library import load_one
from rtupoll.config.site import load_site
from rtupoll.errors import ConfigError, UsageError
from rtupoll.gateway import mbap, rtutcp
from rtupoll.gateway.access import Access, line_settings
from rtupoll.gateway.cache import ReadCache
from rtupoll.gateway.pdu import BadRequest, parse
from rtupoll.rtu import Table, with_crc
from rtupoll.rtu.messages import ReadReply, WriteMultiple, WriteReply, WriteSingle


def frame(tid: int, unit: int, pdu: bytes, *, proto: int = 0, length: int | None = None
          ) -> bytes:
    return struct.pack(">HHHB", tid, proto, len(pdu) + 1 if length is None else length,
                       unit) + pdu


READ = bytes.fromhex("04 75 36 00 05")  # Huiwen: 5 input registers at 30006


# -- MBAP ---------------------------------------------------------------------------
def test_mbap_splits_a_stream_cut_anywhere() -> None:
    stream = frame(1, 3, READ) + frame(2, 4, bytes.fromhex("03 00 00 00 02")) + \
        frame(3, 3, bytes.fromhex("10 00 10 00 02 04 00 01 00 02"))
    for cut in range(1, len(stream)):
        dec = mbap.MbapDecoder()
        got = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        assert [(f.tid, f.unit, f.pdu[0]) for f in got] == [(1, 3, 4), (2, 4, 3), (3, 3, 16)]
        assert dec.buffer == b""


@pytest.mark.parametrize(("data", "why"), [
    (frame(1, 3, READ, proto=1), "protocol id 1"),
    (frame(1, 3, bytes([3]) + bytes(299)), "outside 2..254"),  # a 300-byte PDU
    (frame(1, 3, READ, length=1), "outside 2..254"),
    (frame(1, 3, READ + b"\x00\x00"), "does not match"),  # a read with 2 extra bytes
    (frame(1, 3, bytes.fromhex("10 00 10 00 02 04 00 01 00 02"), length=9) + b"\x00",
     "does not match"),
])
def test_mbap_refuses_frames_it_cannot_trust(data: bytes, why: str) -> None:
    with pytest.raises(mbap.MbapError, match=why):
        mbap.MbapDecoder().feed(data)


def test_mbap_reply_and_exception_encoding() -> None:
    assert mbap.encode(0x1234, 3, b"\x03\x02\x00\x07") == bytes.fromhex(
        "12 34 00 00 00 05 03 03 02 00 07")
    assert mbap.encode_exception(7, 9, 3, 0x0B) == bytes.fromhex("00 07 00 00 00 03 09 83 0b")


# -- RTU over TCP -------------------------------------------------------------------
def test_rtu_over_tcp_frames_and_crc() -> None:
    req = with_crc(bytes.fromhex("01 04 75 36 00 05"))
    dec = rtutcp.RtuDecoder()
    assert dec.feed(req[:3]) == []
    got = dec.feed(req[3:])
    assert [(f.tid, f.unit, f.pdu) for f in got] == [(None, 1, bytes.fromhex("04 75 36 00 05"))]
    assert rtutcp.encode(1, b"\x84\x02") == with_crc(b"\x01\x84\x02")
    with pytest.raises(mbap.MbapError, match="CRC"):
        rtutcp.RtuDecoder().feed(req[:-1] + bytes([req[-1] ^ 1]))


# -- PDUs ---------------------------------------------------------------------------
def test_parse_understands_reads_and_writes() -> None:
    a = parse(READ)
    assert (a.function, a.table, a.address, a.count, a.read, a.write) == \
        (4, Table.INPUT, 0x7536, 5, True, False)
    w = parse(bytes.fromhex("10 00 10 00 02 04 00 01 00 02"))
    assert (w.table, w.address, w.count, w.write) == (Table.HOLDING, 0x10, 2, True)
    assert w.message == WriteMultiple(0, 16, 0x10, (1, 2))
    c = parse(bytes.fromhex("0f 00 00 00 0a 02 05 02"), unit=7)
    assert c.message == WriteMultiple(7, 15, 0, (1, 0, 1, 0, 0, 0, 0, 0, 0, 1))
    assert parse(bytes.fromhex("05 00 d0 ff 00")).message == WriteSingle(0, 5, 0xD0, 1)
    other = parse(bytes.fromhex("08 00 00 12 34"))
    assert (other.table, other.address, other.count, other.read) == (None, 0, 0, False)


@pytest.mark.parametrize(("pdu", "code"), [
    (bytes.fromhex("03 00 00 00 7e"), 3),  # 126 registers
    (bytes.fromhex("03 00 00 00 00"), 3),
    (bytes.fromhex("03 ff ff 00 02"), 2),  # runs past 0xFFFF
    (bytes.fromhex("05 00 d0 12 34"), 3),  # a coil value neither ON nor OFF
    (bytes.fromhex("10 00 10 00 02 03 00 01 00"), 3),  # byte count does not fit
    (bytes.fromhex("41 00"), 1),  # not a Modbus function
    (bytes.fromhex("83 00"), 1),
])
def test_parse_refuses_with_the_servers_exception_code(pdu: bytes, code: int) -> None:
    with pytest.raises(BadRequest) as err:
        parse(pdu)
    assert err.value.code == code


def test_replies_are_the_messages_own_pdus() -> None:
    assert ReadReply(1, 3, (555, 0, 100)).pdu() == bytes.fromhex("03 06 02 2b 00 00 00 64")
    assert ReadReply(1, 1, (1, 0, 1, 1, 0, 0, 0, 0, 1)).pdu() == bytes.fromhex("01 02 0d 01")
    assert WriteReply(1, 6, 0x9C41, 5).pdu() == bytes.fromhex("06 9c 41 00 05")
    assert WriteReply(1, 16, 0x10, 2).pdu() == bytes.fromhex("10 00 10 00 02")


# -- access -------------------------------------------------------------------------
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


# -- cache --------------------------------------------------------------------------
def test_cache_answers_only_what_it_covers_within_age() -> None:
    c = ReadCache(2.0)
    c.put(3, Table.INPUT, 100, [1, 2, 3], at=10.0)
    c.put(3, Table.INPUT, 103, [4], at=11.0)
    assert c.get(3, Table.INPUT, 101, 3, now=11.5) == (2, 3, 4)
    assert c.get(3, Table.INPUT, 101, 4, now=11.5) is None  # 104 was never read
    assert c.get(3, Table.HOLDING, 100, 1, now=11.5) is None
    assert c.get(3, Table.INPUT, 100, 1, now=12.5) is None  # too old
    c.forget(3, Table.INPUT, 102, 1)
    assert c.get(3, Table.INPUT, 101, 2, now=11.0) is None


# -- settings -----------------------------------------------------------------------
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
