"""The one read job (``jobs.device.read_fields``): ``read``, MQTT ``get`` and a poll cycle
send the same requests for the same fields and the same knowledge of the device.

The device is the simulator's Huiwen module with an undocumented hole at input 30011,
inside the 30010..30011 gap its profile lets the planner bridge (the ``hole=`` fault);
each path runs on a fresh ``sim.virtual.VirtualBus`` in virtual time, whose ``sent`` is
every request put on the line.
"""

from __future__ import annotations

import asyncio

from rtupoll.config.library import load_one
from rtupoll.config.site import from_specs
from rtupoll.jobs.device import Read, read_fields
from rtupoll.jobs.scheduler import Backoff, BusPoller
from rtupoll.jobs.stats import Reading, Status
from rtupoll.rtu import Framing, Table
from rtupoll.rtu.messages import ReadRequest, parse_request
from rtupoll.sim.device import SimDeviceConfig
from rtupoll.sim.engine import Engine
from rtupoll.sim.faults import parse_fault
from rtupoll.sim.virtual import VirtualBus, VirtualClock

HOLE = 30011  # wire address (the Huiwen module addresses registers directly)
PINNED = {"pm25": 12, "tvoc": 0.25, "hcho": 0.02, "co2": 800, "temperature": 21,
          "humidity": 40}


def holed() -> tuple[VirtualClock, VirtualBus, BusPoller]:
    """A fresh holed device on a virtual bus, and a poller of its default fields."""
    clock = VirtualClock()
    engine = Engine([SimDeviceConfig(load_one("huiwen-aq"), 3,
                                     faults=(parse_fault(f"3:hole={HOLE}"),))], tick=None)
    for name, value in PINNED.items():
        engine.device(3).pin(name, value)
    bus = VirtualBus(engine, Framing(9600), clock=clock, sleep=clock.sleep)
    config = from_specs("virtual", [("huiwen-aq", 3)], baudrate=9600).buses[0]
    return clock, bus, BusPoller(config, bus, backoff=Backoff(), clock=clock, wall=clock,
                                 rand=lambda: 0.5)


def asked(bus: VirtualBus, since: int = 0) -> list[tuple[int, int, int]]:
    """The reads put on the line (function, address, count), from request ``since``."""
    out = []
    for frame in bus.sent[since:]:
        req = parse_request(frame)
        assert isinstance(req, ReadRequest)
        out.append((req.function, req.address, req.count))
    return out


def cycle(clock: VirtualClock, bp: BusPoller) -> list[Reading]:
    dev = bp.devices[0]
    clock.now = max(clock.now, dev.next_due)
    got: list[Reading] = []
    asyncio.run(bp.run_one(dev, lambda d, rs: got.extend(rs)))
    return got


def test_read_get_and_a_poll_cycle_send_the_same_requests_for_the_same_fields() -> None:
    # rtupoll read: the job with nothing learned (the variant asked where needed)
    _, bus, bp = holed()
    fields = bp.devices[0].config.fields
    profile = bp.devices[0].config.profile
    read = asyncio.run(read_fields(bus, profile, 3, fields, probe=True))
    by_read = asked(bus)
    # a poll cycle, nothing learned yet
    clock, bus, bp = holed()
    readings = cycle(clock, bp)
    by_poll = asked(bus)
    # MQTT get on a poller that has not cycled yet
    _, bus, bp = holed()
    got = asyncio.run(bp.devices[0].read_now(bus, fields))
    by_get = asked(bus)

    assert by_read == by_poll == by_get
    # the block over the hole refused, then bisected: its fields, then the gap halved
    assert by_read[:6] == [(4, 30006, 8), (4, 30006, 4), (4, 30012, 2), (4, 30010, 2),
                           (4, 30010, 1), (4, 30011, 1)]
    assert [r.status for r in readings] == [Status.OK] * len(fields)
    for result in (read, got):
        assert isinstance(result, Read) and result.error() is None and not result.missing
        assert [fv.field.name for fv in result.values] == [f.name for f in fields]
        assert [(b.address, regs) for b, regs in result.holes] == \
            [(30006, frozenset({(Table.INPUT, HOLE)}))]
    values = {fv.field.name: fv.value for fv in read.values}
    assert {fv.field.name: fv.value for fv in got.values} == values
    assert {r.field.name: r.value.value for r in readings if r.value} == values
    assert {n: values[n] for n in PINNED} == PINNED


def test_a_get_plans_around_the_holes_the_poller_learned_and_teaches_it_its_own() -> None:
    # the poller learned the hole in its first cycle: the get reads what its next cycle reads
    clock, bus, bp = holed()
    dev = bp.devices[0]
    cycle(clock, bp)
    n = len(bus.sent)
    got = asyncio.run(dev.read_now(bus, dev.config.fields))
    by_get = asked(bus, n)
    n = len(bus.sent)
    cycle(clock, bp)
    assert by_get == asked(bus, n)
    assert (4, 30006, 4) in by_get and not any(
        a <= HOLE < a + c for _, a, c in by_get)  # never over the hole again
    assert got.error() is None and got.holes == ()

    # a get that found the hole first: the poller's first cycle never asks over it
    clock, bus, bp = holed()
    dev = bp.devices[0]
    asyncio.run(dev.read_now(bus, dev.config.fields))
    assert dev.holes.registers == {(Table.INPUT, HOLE)}
    assert dev.stats.holes and "exception 02 reading input 0x7536+8" in dev.stats.holes[0]
    n = len(bus.sent)
    readings = cycle(clock, bp)
    assert asked(bus, n) == by_get
    assert [r.status for r in readings] == [Status.OK] * len(dev.config.fields)
    assert dev.stats.exceptions[2] == 0


def test_a_get_asks_the_variant_the_poller_did_not_need_and_the_poller_takes_it() -> None:
    """An IRNET-PRO on data structure 0 (no calibration gas level), polled for a field every
    structure has: a get of one that only structure 1 has asks the variant first, as
    ``read`` does, and reports the field not present instead of reading it into
    exception 02."""
    profile = load_one("net-irnet-pro")
    wanted = [profile.field("full_scale"), profile.field("calibration_gas_level")]

    def bus() -> VirtualBus:
        clock = VirtualClock()
        engine = Engine([SimDeviceConfig(profile, 1, variant=0)], tick=None)
        return VirtualBus(engine, Framing(9600), clock=clock, sleep=clock.sleep)

    by_read = bus()
    read = asyncio.run(read_fields(by_read, profile, 1, wanted, probe=True))
    by_get = bus()
    config = from_specs("virtual", [("net-irnet-pro", 1)], baudrate=9600,
                        fields=["concentration"]).buses[0]
    dev = BusPoller(config, by_get, backoff=Backoff()).devices[0]
    assert dev.variant is None and not dev.variant_unknown  # its own fields need none
    got = asyncio.run(dev.read_now(by_get, wanted))
    assert asked(by_get) == asked(by_read) and len(asked(by_read)) == 2  # variant, field
    for result in (read, got):
        assert (result.variant, dict(result.missing)) == (
            0, {"calibration_gas_level": "not present (data structure 0)"})
        assert [fv.field.name for fv in result.values] == ["full_scale"]
        assert result.error() is None and result.refused == ()
    assert dev.variant == 0
