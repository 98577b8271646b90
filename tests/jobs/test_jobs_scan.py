"""The sweep plan and identification, against the simulator's device engine without a port.

The one virtual bus (tests/virtual.py: the simulator's engine, the same devices the pty
server serves, behind the real line discipline) runs on a virtual clock that charges
the full timeout for silence, so identification and the cost of empty addresses are
checked exactly and fast.
The same scans over a real pty and pymodbus are in test_scan_sim.py.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from pathlib import Path

import pytest
from virtual import START, VirtualBus, VirtualClock

from rtupoll.cli.scan import site_yaml
from rtupoll.config.library import load_library, load_profile
from rtupoll.config.site import load_site
from rtupoll.errors import UsageError
from rtupoll.jobs.scan import (
    Found,
    Setting,
    default_baudrates,
    merged,
    parse_addresses,
    presence_probes,
    probe_timeout,
    skipped,
    sweep,
)
from rtupoll.model.profile import Profile
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.line import Line
from rtupoll.sim.device import SimDeviceConfig
from rtupoll.sim.engine import Engine

LIB = sorted(load_library().profiles.values(), key=lambda p: p.id)
BY_ID = {p.id: p for p in LIB}
FIXTURES = Path(__file__).parents[1] / "fixtures"
MARGIN = 0.04


def engine(*specs: tuple[Profile, int]) -> Engine:
    return Engine([SimDeviceConfig(p, a) for p, a in specs], tick=None)


def run_sweep(eng: Engine, addresses: Sequence[int], settings: Sequence[Setting],
              speed: Setting, profiles: Sequence[Profile] = LIB
              ) -> tuple[list[Found], float, list[VirtualBus]]:
    """Sweep ``eng``'s devices, which answer only at ``speed``; (found, the virtual time it
    took, the bus opened for each setting)."""
    clock = VirtualClock(START)
    buses: list[VirtualBus] = []

    @asynccontextmanager
    async def open_bus(s: Setting) -> AsyncIterator[VirtualBus]:
        # at another speed a device hears noise and says nothing: an engine with no devices
        heard = eng if s == speed else Engine([], tick=None)
        bus = VirtualBus(heard, s.framing, clock=clock, sleep=clock.sleep)
        bus.line = Line(s.framing, drain=0.0)  # as ``rtupoll scan`` opens its bus
        buses.append(bus)
        yield bus

    found: list[Found] = []
    asyncio.run(sweep(open_bus, settings, addresses, profiles, margin=MARGIN,
                      probes=presence_probes(profiles), found=found))
    return merged(found), clock.now - START, buses


SEEDS = [(BY_ID["net-irnet-pro"], 3), (BY_ID["radar-level"], 7), (BY_ID["huiwen-aq"], 12),
         (BY_ID["co2meter-an117"], 20), (BY_ID["banner-ez-array"], 31)]


def test_five_seed_devices_at_mixed_addresses_are_each_identified() -> None:
    found, _, _ = run_sweep(engine(*SEEDS), range(1, 40), [Setting(9600)], Setting(9600))
    assert [(f.address, f.profile.id if f.profile else None) for f in found] == \
        [(a, p.id) for p, a in SEEDS]
    irnet = found[0]
    assert any(e.startswith("data_structure") for e in irnet.evidence)
    huiwen = found[2]
    assert "slave_address = 12 (its own address)" in huiwen.evidence


def test_devices_are_found_at_their_speed_not_the_first_tried() -> None:
    speed = Setting(19200)
    found, _, _ = run_sweep(engine(*SEEDS[:2]), range(1, 10),
                            [Setting(9600), Setting(19200), Setting(38400)], speed)
    assert [(f.address, f.setting) for f in found] == [(3, speed), (7, speed)]


def test_a_device_with_no_profile_in_the_library_is_unknown_with_its_answers() -> None:
    stranger = load_profile(FIXTURES / "scan" / "acme-meter.yaml")
    found, _, _ = run_sweep(engine((stranger, 5)), range(1, 8), [Setting(9600)], Setting(9600))
    (f,) = found
    assert f.status == "unknown" and f.profile is None
    assert f.answers and all("input 0x0001" in a or ":" in a for a in f.answers)


def test_the_same_device_is_identified_once_its_profile_is_in_the_library() -> None:
    stranger = load_profile(FIXTURES / "scan" / "acme-meter.yaml")
    found, _, _ = run_sweep(engine((stranger, 5)), [5], [Setting(9600)], Setting(9600),
                            [*LIB, stranger])
    assert found[0].profile is stranger


def test_an_empty_range_costs_one_derived_timeout_per_address() -> None:
    found, elapsed, buses = run_sweep(engine(), range(1, 101), [Setting(9600)], Setting(9600))
    assert found == []
    assert len(buses[0].sent) == 100  # one probe per address, nothing else
    framing = Framing(9600)
    per = probe_timeout(framing, 1, MARGIN)
    assert elapsed == pytest.approx(100 * per)


def test_identifying_a_silent_device_stays_within_a_few_requests() -> None:
    _, _, buses = run_sweep(engine((BY_ID["co2meter-an117"], 9)), [9], [Setting(115200)],
                            Setting(115200))
    assert len(buses[0].sent) <= 1 + sum(len(p.identify) for p in LIB)


def test_the_presence_probe_is_one_read_a_silent_device_answers() -> None:
    probes = presence_probes(LIB)
    assert probes == [(Table.INPUT, 1, 1)]  # the CO2Meter's own CO2 register
    assert 4 in BY_ID["co2meter-an117"].limits.functions


def test_probe_timeout_is_wire_time_silence_and_margin() -> None:
    framing = Framing(9600)  # 10 bits per character: 1.0417 ms
    expected = (8 + 7) * 10 / 9600 + 3.5 * 10 / 9600 + MARGIN
    assert probe_timeout(framing, 1, MARGIN) == pytest.approx(expected)
    assert probe_timeout(Framing(115200), 1, MARGIN) == pytest.approx(
        15 * 10 / 115200 + 0.00175 + MARGIN)


def test_broadcast_any_and_reserved_addresses_are_skipped_and_say_why() -> None:
    why = skipped(range(0, 256), LIB)
    assert set(why) == {0, 0xFE, 0xCC, 0xF8, 0xFF}
    assert "co2meter-an117" in why[0xFE]
    assert "peacefair-pzem016" in why[0xF8]  # the PZEM's "general address"
    assert "every r4dcb08" in why[0xFF]  # the R4DCB08 answers 255 whatever its address


def test_address_lists_and_their_errors() -> None:
    assert parse_addresses("1-3,100,2") == (1, 2, 3, 100)
    with pytest.raises(UsageError):
        parse_addresses("5-300")
    with pytest.raises(UsageError):
        parse_addresses("x")


def test_default_baud_rates_put_the_common_defaults_first() -> None:
    rates = default_baudrates(LIB)
    assert rates[0] == 9600 and set(rates) >= {4800, 9600, 19200, 38400, 115200}


def test_written_site_file_loads_and_leaves_out_what_cannot_share_the_bus(
        tmp_path: Path) -> None:
    s = Setting(9600)
    found = [Found(3, s, BY_ID["net-irnet-pro"]), Found(12, s, BY_ID["huiwen-aq"]),
             Found(20, s, BY_ID["co2meter-an117"]),  # only runs at 115200
             Found(40, s, None, answers=["input 0x0001: exception 02 ILLEGAL DATA ADDRESS"])]
    text, notes = site_yaml("/dev/ttyUSB0", found, [])
    assert text is not None
    path = tmp_path / "site.yaml"
    path.write_text(text)
    site = load_site(path)
    assert [(d.profile.id, d.address) for _, d in site.devices()] == \
        [("net-irnet-pro", 3), ("huiwen-aq", 12)]
    assert site.buses[0].baudrate == 9600
    assert any("co2meter-an117" in n and "115200" in n for n in notes)
    assert any("unknown device at 40" in n for n in notes)


def test_the_site_file_takes_the_setting_most_found_devices_can_run_at() -> None:
    # a bus that answered at every speed tried (a forgiving adapter, or the untimed
    # simulator): 4800 comes first, but only the IRNET runs there; four run at 9600
    found = [Found(a, Setting(rate), BY_ID[pid]) for rate in (4800, 9600)
             for pid, a in (("net-irnet-pro", 1), ("radar-level", 2), ("huiwen-aq", 3),
                            ("banner-ez-array", 5))]
    text, _ = site_yaml("/dev/ttyUSB0", found, [])
    assert text is not None and "baudrate: 9600" in text
    assert text.count("profile:") == 4
