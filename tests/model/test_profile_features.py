"""Profile features the device library needs: bit fields, sentinels, precision (and
floats at their type's precision), per-field poll intervals, counters, ``extends``."""

from __future__ import annotations

import asyncio
import json
import struct
from pathlib import Path
from textwrap import dedent

import pytest
from cli_runner import rtupoll
from virtual import heard_nothing

from rtupoll.config.library import load_one, load_profile
from rtupoll.config.site import DeviceConfig
from rtupoll.errors import EncodeError, ProfileError
from rtupoll.jobs.scheduler import DevicePoller
from rtupoll.jobs.stats import BusLoad
from rtupoll.model.codec import DataType, Layout, decode, encode
from rtupoll.model.interpret import field_words, interpret
from rtupoll.model.planner import plan
from rtupoll.model.record import record
from rtupoll.rtu import Table
from rtupoll.rtu.line import UnitCounts
from rtupoll.rtu.transaction import Evidence, ReadResult
from rtupoll.sim.device import SimDevice
from rtupoll.sim.device import SimDeviceConfig as SimConfig
from rtupoll.ui.records import CsvWriter, to_json

HEADER = """\
id: {id}
vendor: ACME
kind: test meter
model: M1
manual: M1 manual rev 2
addressing: pdu
identify:
  - {{field: voltage, range: [100, 300]}}
"""


def write(tmp: Path, pid: str, body: str, header: str = HEADER) -> Path:
    path = tmp / f"{pid}.yaml"
    path.write_text(header.format(id=pid) + dedent(body), encoding="utf-8")
    return path


METER = """\
fields:
  - {name: voltage, table: input, address: 0, type: f32, unit: V, typical: 230.1}
  - {name: energy, table: input, address: 2, type: u32, scale: 0.01, unit: kWh,
     counter: true, interval: 60, typical: 1234.56}
  - {name: temperature, table: input, address: 4, type: i16, scale: 0.1, unit: "°C",
     precision: 1, sentinels: {0x8000: {name: SENSOR_ERROR, severity: error},
                               0x7FFF: NOT_AVAILABLE}}
  - {name: state, table: input, address: "5:0:4", type: u16,
     enum: {0: NORMAL, 2: {name: UNDERVOLTAGE, severity: warning}}}
  - {name: temp_state, table: input, address: 5:4:4, type: u16}
  - {name: offset_bits, table: input, address: "0x0005:8:3", type: i16}
  - {name: wrong_voltage, table: input, address: "5:15:1", type: u16, enum: {0: "NO", 1: "YES"}}
  - {name: power, table: input, address: 6, type: f32, unit: W, precision: 0}
"""


@pytest.fixture
def meter(tmp_path: Path) -> Path:
    return write(tmp_path, "acme-m1", METER)


# -- bit fields ---------------------------------------------------------------

def test_bit_fields_decode_their_bits_and_share_a_register(meter: Path) -> None:
    p = load_profile(meter)
    word = (1 << 15) | (0b101 << 8) | (0x3 << 4) | 0x2  # D15, D10-8 = -3, D7-4 = 3, D3-0 = 2
    values = {n: interpret(p.field(n), [word]).value
              for n in ("state", "temp_state", "offset_bits", "wrong_voltage")}
    assert values == {"state": "UNDERVOLTAGE", "temp_state": 3, "offset_bits": -3,
                      "wrong_voltage": "YES"}
    assert p.field("temp_state").written == "0x0005 bits 4-7"  # unquoted 5:4:4 too
    assert len(plan(p.fields, p)) == 1  # the shared register is read once


def test_writing_a_bit_field_keeps_the_other_bits() -> None:
    layout = Layout(DataType.U16, shift=4, width=3)
    assert encode(5, layout, current=[0xFF0F]) == (0xFF5F,)
    assert decode([0xFF5F], layout) == 5
    with pytest.raises(EncodeError, match=r"outside 3 bits \(0\.\.7\)"):
        encode(8, layout)
    signed = Layout(DataType.I16, shift=0, width=4)
    assert encode(-1, signed, current=[0xABC0]) == (0xABCF,)
    assert decode([0xABCF], signed) == -1


@pytest.mark.parametrize(("field", "message"), [
    ('{name: a, table: input, address: "1:14:4", type: u16}',
     "bits 14..17 are not inside one 16-bit register"),
    ('{name: a, table: input, address: "1:4:4", type: f32}',
     "a bit field is u16 or i16 in a register, not f32"),
    ('{name: a, table: input, address: "1:x:4", type: u16}', "is not REGISTER:SHIFT:WIDTH"),
])
def test_bad_bit_fields_are_one_line_errors(tmp_path: Path, field: str, message: str) -> None:
    path = write(tmp_path, "acme-bad", f"fields:\n  - {field}\n")
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert str(exc.value).startswith(f"{path}:10: fields[0].address: ")
    assert message in str(exc.value)


def test_bit_fields_whose_bits_overlap_are_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "acme-bad", """\
        fields:
          - {name: voltage, table: input, address: 0, type: u16}
          - {name: a, table: input, address: "0:0:4", type: u16}
        """)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert str(exc.value) == (f"{path}:11: fields[1]: a overlaps voltage (line 10) in the "
                              f"input table")


def test_a_bit_field_and_a_field_of_the_same_name_are_one_line(tmp_path: Path) -> None:
    path = write(tmp_path, "acme-twice", """\
        fields:
          - {name: voltage, table: input, address: 0, type: u16}
          - {name: a, table: input, address: "1:0:4", type: u16}
          - {name: a, table: input, address: 2, type: u16}
        """)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert str(exc.value) == (f"{path}:12: fields[2]: duplicate field name 'a' "
                              f"(first at line 11)")


# -- sentinels ----------------------------------------------------------------

def test_a_sentinel_is_reported_by_name_with_a_null_value(meter: Path) -> None:
    f = load_profile(meter).field("temperature")
    fv = interpret(f, [0x8000])
    assert (fv.present, fv.output, fv.text, fv.severity.value) == \
        (False, None, "SENSOR_ERROR", "error")
    rec = record("m@1", "acme-m1", 1, fv)
    assert json.loads(to_json(rec))["value"] is None
    assert (rec["text"], rec["severity"], rec["raw"]) == ("SENSOR_ERROR", "error", [0x8000])
    assert interpret(f, [0x7FFF]).severity.value == "warning"  # a bare name: not "ok"
    assert interpret(f, [215]).output == 21.5


def test_a_sentinel_row_in_csv_has_an_empty_value_and_the_name(meter: Path) -> None:
    import io

    out = io.StringIO()
    w = CsvWriter(out, ("field", "value", "text"))
    w.write(record("m@1", "acme-m1", 1, interpret(load_profile(meter).field("temperature"),
                                                 [0x7FFF])))
    assert out.getvalue().splitlines() == ["field,value,text", "temperature,,NOT_AVAILABLE"]


def test_a_sentinel_that_does_not_fit_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "acme-bad", """\
        fields:
          - {name: voltage, table: input, address: 0, type: u16, sentinels: {0x10000: N_A}}
        """)
    with pytest.raises(ProfileError, match=r":10: fields\[0\]\.sentinels\.0x10000: sentinel "
                                           r"65536 does not fit the field \(0\.\.65535\)"):
        load_profile(path)


# -- floats and precision -----------------------------------------------------

def test_an_f32_prints_at_its_own_precision_in_json_and_the_table() -> None:
    f = load_one("net-irnet-pro").field("temperature")  # f32, DCBA, kelvin
    words = field_words(f, 296.15)
    assert struct.unpack("<f", struct.pack("<HH", *words))[0] != 296.15  # not exact in f32
    fv = interpret(f, words)
    assert fv.value == 296.15 and fv.text == "296.15"
    assert '"value":296.15,' in to_json(record("irnet@1", "net-irnet-pro", 1, fv))


def test_precision_rounds_the_value_and_its_text(meter: Path) -> None:
    p = load_profile(meter)
    assert interpret(p.field("temperature"), [215]).text == "21.5"
    power = interpret(p.field("power"), field_words(p.field("power"), 1234.56))
    assert (power.value, power.text) == (1235, "1235")


# -- intervals ----------------------------------------------------------------

def test_the_poll_plan_keeps_slow_fields_in_blocks_of_their_own(meter: Path) -> None:
    p = load_profile(meter)
    assert [b.interval for b in plan(p.fields, p, by_interval=True)] == [None, 60.0, None]
    assert len(plan(p.fields, p)) == 1  # a one-off read takes everything at once


class CountingTransport:
    """Answers every read with zeros and remembers what was read."""

    def __init__(self) -> None:
        self.reads: list[tuple[int, int]] = []

    async def open(self) -> None: ...
    async def close(self) -> None: ...

    async def read(self, unit: int, table: Table, address: int, count: int, *,
                   timeout: float, retries: int = 0, patience: float = 0.0,
                   idle_gap: float | None = None) -> ReadResult:
        self.reads.append((address, count))
        return ReadResult((0,) * count, Evidence())  # nothing measured

    adapter_latency = 0.0  # BusLike: no USB adapter
    echo_found = False  # BusLike: no line to hear an echo
    stats = None  # BusLike: counts nothing

    def unit_counts(self, unit: int) -> UnitCounts:
        return heard_nothing(unit)  # no late replies


def test_the_scheduler_reads_a_slow_field_once_per_its_interval(meter: Path) -> None:
    p = load_profile(meter)
    now = [1000.0]
    poller = DevicePoller(DeviceConfig("m", p, 1, p.default_fields(), interval=1.0),
                          BusLoad(0.0), clock=lambda: now[0], wall=lambda: now[0])
    bus = CountingTransport()
    seen = []
    for t in (1000.0, 1001.0, 1030.0, 1060.0, 1061.0):
        now[0] = t
        readings = asyncio.run(poller.cycle(bus))
        seen.append("energy" in {r.field.name for r in readings})
        assert poller.stats.failures == 0
    assert seen == [True, False, False, True, False]
    assert bus.reads.count((2, 2)) == 2


# -- counters and the simulator ----------------------------------------------

def test_a_counter_is_marked_and_only_grows_in_the_simulator(meter: Path) -> None:
    p = load_profile(meter)
    assert p.field("energy").counter and not p.field("voltage").counter
    dev = SimDevice(SimConfig(p, 1), seed=3)
    assert dev.value("energy").value == 1234.56  # the profile's typical value
    assert dev.value("voltage").value == 230.1
    last = 0.0
    for _ in range(50):
        dev.advance()
        value = dev.value("energy").value
        assert isinstance(value, float) and value >= last
        last = value
    assert last > 1234.56


def test_counter_needs_a_number(tmp_path: Path) -> None:
    path = write(tmp_path, "acme-bad", """\
        fields:
          - {name: voltage, table: input, address: 0, type: u16, counter: true,
             enum: {0: OFF}}
        """)
    with pytest.raises(ProfileError, match="only a number can be a counter"):
        load_profile(path)


# -- extends ------------------------------------------------------------------

CHILD = """\
id: {id}
extends: acme-m1
model: M2 (no temperature sensor)
without: [temperature]
fields:
  - {{name: voltage, table: input, address: 0, type: f32, unit: V, precision: 1}}
  - {{name: frequency, table: input, address: 10, type: f32, unit: Hz}}
"""


def test_a_profile_extends_another(meter: Path) -> None:
    child = load_profile(write(meter.parent, "acme-m2", "", header=CHILD))
    parent = load_profile(meter)
    assert child.extends == "acme-m1" and child.model.startswith("M2")
    assert child.vendor == parent.vendor and child.identify == parent.identify
    assert child.names() == [n for n in parent.names() if n != "temperature"] + ["frequency"]
    assert child.field("voltage").precision == 1 and parent.field("voltage").precision is None
    assert child.field("energy") == parent.field("energy")


def test_an_inherited_mistake_points_at_the_parent_file(tmp_path: Path) -> None:
    parent = write(tmp_path, "acme-m1", """\
        fields:
          - {name: voltage, table: input, address: 0, type: f32}
          - {name: energy, table: input, address: 2, type: f32, unti: kWh}
          - {name: temperature, table: input, address: 4, type: i16}
        """)
    child = write(tmp_path, "acme-m2", "", header=CHILD)
    with pytest.raises(ProfileError) as exc:
        load_profile(child)
    assert str(exc.value).startswith(f"{parent}:11: fields[1].unti: unknown key")


@pytest.mark.parametrize(("extends", "without", "message"), [
    ("acme-none", "[]", "no profile 'acme-none' next to this file or on the profile search path"),
    ("acme-m1", "[no_such]", "acme-m1 has no field 'no_such' to drop"),
    ("acme-m2", "[]", "'acme-m2' extends this profile: a loop"),
])
def test_extends_mistakes(meter: Path, extends: str, without: str, message: str) -> None:
    path = meter.parent / "acme-m2.yaml"
    path.write_text(f"id: acme-m2\nextends: {extends}\nwithout: {without}\n", encoding="utf-8")
    result = rtupoll("profiles", "check", str(path))
    assert result.returncode == 2
    assert message in result.stderr.splitlines()[0]
    assert result.stderr.startswith(f"{path}:")


def test_profiles_show_lists_the_new_attributes(meter: Path) -> None:
    result = rtupoll("profiles", "show", str(meter), env={"COLUMNS": "160"})
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "ir 0x0005 bits 4-7" in out
    assert "[counter] [every 60 s]" in out
    assert "[0x8000 = SENSOR_ERROR] [0x7FFF = NOT_AVAILABLE]" in out


def test_a_writable_bit_field_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, "acme-bad", """\
        fields:
          - {name: voltage, table: holding, address: "0:0:4", type: u16, access: RW}
        """)
    with pytest.raises(ProfileError, match=r":10: fields\[0\]\.access: bit fields are read-only"):
        load_profile(path)


def test_a_big_f32_total_prints_positional(meter: Path) -> None:
    f = load_profile(meter).field("voltage")  # f32, no precision
    assert interpret(f, field_words(f, 35565090.0)).text == "35565090"
    assert interpret(f, field_words(f, 50.0)).text == "50"
    assert interpret(f, field_words(f, 0.1)).text == "0.1"


def test_the_simulator_can_show_a_sentinel_and_poll_reports_it(meter: Path) -> None:
    """A simulated device takes a sentinel's name; the poll record is null with the name."""
    from rtupoll.sim.runner import simulated_bus

    with simulated_bus(["acme-m1@1"], tcp=True, tick=None, profile_dirs=[meter.parent]) as bus:
        bus.set(1, "temperature", "SENSOR_ERROR")
        result = rtupoll("poll", "--profiles", str(meter.parent), "--port",
                         bus.port, "--once", "--format", "json",
                         "acme-m1@1")
    assert result.returncode == 0, result.stderr
    recs = {r["field"]: r for r in map(json.loads, result.stdout.splitlines())}
    temp = recs["temperature"]
    assert (temp["value"], temp["text"], temp["severity"], temp["raw"], temp["status"]) == \
        (None, "SENSOR_ERROR", "error", [0x8000], "ok")
    assert recs["voltage"]["value"] == 230.1
