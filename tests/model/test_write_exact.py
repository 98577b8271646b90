"""A write lands as asked or is refused before sending (issue 24 section 3): one check
(``codec.check_exact``) of a value against its type, for u16/i16/u32/i32/f32/f64 and
scaled fields, on the CLI and the MQTT path alike; an interrupted ``write`` says the
write may have been applied."""

from __future__ import annotations

import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable

import pytest
from cli_runner import rtupoll
from forked_cli import rtupoll_popen
from hypothesis import given, settings
from hypothesis import strategies as st

from rtupoll.config.library import load_one
from rtupoll.errors import RefusedError
from rtupoll.jobs.writes import plan_write
from rtupoll.model.codec import ByteOrder, DataType, Layout
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Field
from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
FUNCTIONS = frozenset({3, 6, 16})


def field(kind: str, scale: float = 1.0, offset: float = 0.0) -> Field:
    t = DataType(kind)
    words = 1 if kind in ("u16", "i16") else 4 if kind == "f64" else 2
    return Field(name="x", table=Table.HOLDING, address=0, access="RW",
                 layout=Layout(t, words, ByteOrder.ABCD, scale=scale, offset=offset))


def stored_f32(x: float) -> float:
    return float(struct.unpack(">f", struct.pack(">f", x))[0])


@pytest.mark.parametrize(("kind", "scale", "text", "why"), [
    ("u16", 1, "65536", "outside"), ("u16", 1, "-1", "outside"), ("u16", 1, "1.5", "whole"),
    ("i16", 1, "32768", "outside"), ("i16", 1, "-32769", "outside"),
    ("u32", 1, "4294967296", "outside"), ("i32", 1, "2147483648", "outside"),
    ("f32", 1, "99999999", "would read back as 100000000"),
    ("f32", 1, "16777217", "would read back as 16777216"),
    ("f32", 1, "1e39", "outside"), ("f32", 1, "-1e39", "outside"),
    ("f64", 1, "9007199254740993", "would read back as 9007199254740992"),
    ("u16", 0.1, "25.37", "resolution"), ("u16", 0.1, "6553.6", "outside"),
])
def test_a_value_the_type_cannot_hold_is_refused_before_sending(
        kind: str, scale: float, text: str, why: str) -> None:
    with pytest.raises(RefusedError, match=why):
        plan_write(field(kind, scale), text, FUNCTIONS)


@pytest.mark.parametrize(("kind", "scale", "text", "value"), [
    ("u16", 1, "65535", 65535), ("i16", 1, "-32768", -32768), ("u32", 1, "4294967295",
                                                                 4294967295),
    ("i32", 1, "-2147483648", -2147483648), ("f32", 1, "0.1", 0.1),
    ("f32", 1, "100000000", 100000000), ("f32", 1, "3.4028235e38", 3.4028235e38),
    ("f64", 1, "0.1", 0.1), ("u16", 0.1, "25.3", 25.3), ("i16", 100, "9600", 9600),
])
def test_a_value_the_type_holds_is_planned_and_reads_back_as_itself(
        kind: str, scale: float, text: str, value: float) -> None:
    f = field(kind, scale)
    op = plan_write(f, text, FUNCTIONS)
    assert interpret(f, op.words).value == value


@settings(max_examples=max(400, settings().max_examples), deadline=None, derandomize=True)
@given(st.sampled_from(["u16", "i16", "u32", "i32", "f32", "f64"]),
       st.sampled_from([1.0, 0.1, 0.01, 10.0]),
       st.one_of(st.integers(-2**40, 2**40), st.floats(allow_nan=False, allow_infinity=False,
                                                        width=64)))
def test_whatever_is_planned_reads_back_as_the_value_written(kind: str, scale: float,
                                                              number: float) -> None:
    """The reading path (``interpret``) is the judge: a planned write never reads back
    as anything but the value asked for; everything else is refused (exit 8)."""
    f = field(kind, scale)
    try:
        op = plan_write(f, repr(number), FUNCTIONS)
    except RefusedError:
        assert not must_fit(kind, scale, number), (kind, scale, number)
        return
    assert interpret(f, op.words).value == number


RANGES = {"u16": (0, 2**16 - 1), "i16": (-2**15, 2**15 - 1), "u32": (0, 2**32 - 1),
          "i32": (-2**31, 2**31 - 1)}


def must_fit(kind: str, scale: float, number: float) -> bool:
    """Values the type holds exactly, which no check may refuse."""
    if scale != 1:
        return False
    if kind in RANGES:
        lo, hi = RANGES[kind]
        return isinstance(number, int) and lo <= number <= hi
    if kind == "f64":
        return isinstance(number, float) or abs(number) <= 2**53
    return isinstance(number, float) and abs(number) < 3e38 and \
        stored_f32(number) == number and len(repr(number)) <= 12


def test_the_irnet_gas_level_99999999_exits_8_and_nothing_is_sent(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    result = rtupoll("write", "-p", bus.port, "-b", "9600", "net-irnet-pro@1",
                     "calibration_gas_level=99999999", "--yes")
    assert result.returncode == 8, (result.stdout + result.stderr)
    assert "would read back as 100000000" in (result.stdout + result.stderr)
    assert [w for w in bus.wire if w.direction == "in"] == []


def test_the_mqtt_path_refuses_1e39_through_the_same_check() -> None:
    p = load_one("net-irnet-pro")
    with pytest.raises(RefusedError, match="outside what f32 holds"):
        plan_write(p.field("calibration_gas_level"), "1e39", p.limits.functions)


def test_write_interrupted_after_the_request_went_out_says_it_may_have_been_applied(
        sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", faults=["1:dead"], tick=None)
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "write", "-p", bus.port,
                          "-b", "9600", "--timeout", "10", "--retries", "0", "--yes",
                          "net-irnet-pro@1", "calibration_gas_level=2500"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
    while not [w for w in bus.wire if w.direction == "in" and w.data[1:2] == b"\x10"]:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 130, err
    assert "may have been applied" in err and "calibration_gas_level = 2500" in err, err
    assert "Traceback" not in err
