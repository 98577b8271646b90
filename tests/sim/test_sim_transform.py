"""A simulated meter whose power factor register holds Schneider's four-quadrant code
(``decode: four_quadrant_pf``): it serves the code for the value it is set to, keeps a
moving power factor inside -1..+1 (the encoding's span), refuses a value no power factor
has, and the real ``rtupoll read`` over a pty reads back what was set."""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable

import pytest
from cli_runner import rtupoll

from rtupoll.errors import RefusedError
from rtupoll.rtu.messages import ReadRequest
from rtupoll.sim.engine import Engine
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import build

IEM = "schneider-iem3155@1"


def make(*sets: str) -> Engine:
    config = build([IEM], sets=list(sets))
    return Engine(config.devices, config.faults, seed=config.seed, tick=None)


def test_the_register_holds_a_code_that_unfolds_to_the_value_set() -> None:
    e = make(f"{IEM}.total_power_factor=-0.7")
    # register 3084 (one-based) is wire 3083: a big-endian Float32 in -1..+1
    reply = b"".join(t.data for t in e.handle(ReadRequest(1, 3, 3083, 2).frame()))
    (stored,) = struct.unpack(">f", reply[3:7])
    assert stored == pytest.approx(-0.7, abs=1e-6)


def test_a_moving_power_factor_stays_inside_the_encodings_span() -> None:
    e = make()
    dev = e.devices[0]
    seen = []
    for _ in range(400):
        dev.advance(1)
        fv = dev.value("total_power_factor")
        assert isinstance(fv.value, float) and not math.isnan(fv.value)
        seen.append(fv.value)
    assert min(seen) >= -1.0 and max(seen) <= 1.0 and len(set(seen)) > 10


def test_a_power_factor_above_one_cannot_be_set() -> None:
    with pytest.raises(RefusedError, match="outside what four_quadrant_pf holds"):
        make(f"{IEM}.total_power_factor=1.3")


def test_rtupoll_read_gets_the_power_factor_the_meter_was_set_to(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim(IEM, tick=None, sets=[f"{IEM}.total_power_factor=0.95"])
    run = rtupoll("read", "-p", bus.port, "--format", "json", IEM, "total_power_factor")
    assert run.returncode == 0, run.stderr
    record = json.loads(run.stdout)
    assert record["field"] == "total_power_factor" and record["value"] == 0.95
