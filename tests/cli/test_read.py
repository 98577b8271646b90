"""`rtupoll read` against the simulator: every seed device by field name, raw registers in
each addressing form, the output formats, and the failures a technician meets."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import conftest
import pytest
from cli_runner import Ran, rtupoll

from rtupoll.config.library import load_one
from rtupoll.model.record import READ_KEYS
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]

PATIENT = (*conftest.PATIENT, "--retries", "0")


def run(*args: str) -> Ran:
    return rtupoll(*args)


def records(result: Ran) -> list[dict[str, Any]]:
    assert result.returncode == 0, (result.stdout + result.stderr)
    return [json.loads(line) for line in result.stdout.splitlines()]


def requests(bus: SimulatedBus) -> list[str]:
    """The frames the master sent, as hex."""
    return [w.data.hex(" ").upper() for w in bus.wire if w.direction == "in"]


@pytest.mark.parametrize(("device", "sets", "field", "value"), [
    ("net-irnet-pro@1", ("concentration=-20.0",), "concentration", -20.0),
    ("net-irnet-pro@1", ("error=FLASH_CKSM_ERROR",), "error", "FLASH_CKSM_ERROR"),
    ("net-irnet-pro@1", ("warning=WARMUP_WARNING,HW_TEST_WARNING",), "warning",
     ["WARMUP_WARNING", "HW_TEST_WARNING"]),
    ("radar-level@1", ("level_cm=123",), "level_cm", 123),
    ("huiwen-aq@1", ("co2=5000",), "co2", 5000),
    ("huiwen-aq@1", ("co2_level=MODERATE",), "co2_level", "MODERATE"),
    ("co2meter-an117@0xFE", ("co2=400",), "co2", 400),
    ("banner-ez-array@1", ("holding_40001=555",), "holding_40001", 555),
    ("banner-ez-array@1", ("measurement_1_mode=TBB",), "measurement_1_mode", "TBB"),
])
def test_every_seed_device_reads_by_field_name(device: str, sets: tuple[str, ...], field: str,
                                               value: object, sim: Sim) -> None:
    pin = [f"{device}.{s}" for s in sets]
    bus = sim(device, sets=pin, tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json", device, field))
    assert [r["field"] for r in recs] == [field]
    assert recs[0]["value"] == value
    assert recs[0]["device"] == device.replace("0xFE", "254")
    assert tuple(recs[0]) == READ_KEYS


def test_golden_frame_of_the_co2meter_manual_goes_on_the_wire(sim: Sim) -> None:
    bus = sim("co2meter-an117@254", sets=["co2meter-an117@254.co2=400"], tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json",
                       "co2meter-an117@254", "co2"))
    assert "FE 04 00 01 00 01 74 05" in requests(bus)
    assert recs[0]["raw"] == [400]


def test_without_fields_the_profiles_default_set_is_read(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json", "huiwen-aq@1"))
    assert [r["field"] for r in recs] == [f.name for f in load_one("huiwen-aq").default_fields()]
    assert all(r["value"] is not None for r in recs)


def test_csv_has_the_json_keys_as_header(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", sets=["net-irnet-pro@1.warning=0"], tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--format", "csv", "net-irnet-pro@1",
                 "warning", "temperature")
    lines = result.stdout.splitlines()
    assert result.returncode == 0 and lines[0] == ",".join(READ_KEYS)
    assert lines[1].startswith("net-irnet-pro@1,net-irnet-pro,1,warning,,")  # no flags: empty
    assert len(lines) == 3


def test_table_for_people_names_device_fields_and_units(sim: Sim) -> None:
    bus = sim("huiwen-aq@1", sets=["huiwen-aq@1.temperature=-5"], tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--hex", "huiwen-aq@1", "temperature", "co2")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert "huiwen-aq@1" in result.stdout and "°C" in result.stdout
    row = next(line for line in result.stdout.splitlines() if "temperature" in line)
    assert "-5" in row and "FFFB" in row and "input 30012" in row


# -- raw registers --------------------------------------------------------------------


def test_raw_read_of_the_huiwen_manuals_example_sends_its_frame(sim: Sim) -> None:
    pins = [f"huiwen-aq@1.{s}" for s in ("pm25=25", "tvoc=0.05", "hcho=0.25", "co2=5000")]
    bus = sim("huiwen-aq@1", sets=pins, tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json", "--raw", "1",
                       "input:30006:5"))
    assert requests(bus) == ["01 04 75 36 00 05 CA 0B"]
    assert [r["field"] for r in recs][:2] == ["input:30006", "input:30007"]
    assert [r["value"] for r in recs][:4] == [25, 50, 250, 5000]
    assert recs[0]["profile"] == "" and recs[0]["device"] == "1"


@pytest.mark.parametrize(("flags", "spec"), [
    ((), "holding:2"),
    ((), "holding:0x0002"),
    (("--one-based",), "holding:3"),
    (("--modicon",), "40003"),
    (("--modicon",), "holding:40003"),
])
def test_raw_read_in_each_addressing_form_reaches_the_same_register(
        flags: tuple[str, ...], spec: str, sim: Sim) -> None:
    bus = sim("radar-level@1", sets=["radar-level@1.level_cm=321"], tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json", "--raw", *flags,
                       "radar-level@1", spec))
    assert requests(bus) == ["01 03 00 02 00 01 25 CA"]  # wire address 2, as sent
    assert recs[0]["value"] == 321
    # labelled as written (a Modicon reference by itself)
    assert recs[0]["field"] == (spec.removeprefix("holding:") if "--modicon" in flags else spec)


def test_raw_float_in_the_irnets_byte_order(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", sets=["net-irnet-pro@1.concentration=-20"], tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json", "--raw",
                       "--type", "f32", "--order", "DCBA", "1", "input:6"))
    assert requests(bus) == ["01 04 00 06 00 02 91 CA"]  # the manual's golden request
    assert recs[0]["value"] == -20.0 and recs[0]["raw"] == [0x0000, 0xA0C1]


def test_raw_read_with_a_profile_takes_its_byte_order_and_splits_at_its_limit(sim: Sim) -> None:
    bus = sim("co2meter-an117@0x68", tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--format", "json", "--raw",
                 "co2meter-an117@0x68", "input:1:1")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert len(requests(bus)) == 1


def test_raw_table_with_hex_shows_the_words(sim: Sim) -> None:
    bus = sim("radar-level@1", sets=["radar-level@1.level_cm=255"], tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--raw", "--hex", "1", "holding:0x2")
    assert result.returncode == 0, (result.stdout + result.stderr)
    assert "holding:0x0002" in result.stdout and "00FF" in result.stdout


# -- refusals and the IRNET variant ----------------------------------------------------


def test_a_never_polled_field_is_refused_unless_forced(sim: Sim) -> None:
    bus = sim("banner-ez-array@1", tick=None)
    refused = run("read", "-p", bus.port, *PATIENT, "banner-ez-array@1", "analog_1_peak")
    assert requests(bus) == []
    forced = run("read", "-p", bus.port, *PATIENT, "--force", "--format", "json",
                 "banner-ez-array@1", "analog_1_peak")
    assert refused.returncode == 8
    assert "analog_1_peak is never read unless forced" in refused.stderr
    assert "RESETS THE PEAK" in refused.stderr and "--force" in refused.stderr
    assert records(forced)[0]["field"] == "analog_1_peak"


def test_the_default_set_never_touches_a_never_polled_register(sim: Sim) -> None:
    bus = sim("banner-ez-array@1", tick=None)
    run("read", "-p", bus.port, *PATIENT, "--format", "json", "banner-ez-array@1")
    reads = [w.data for w in bus.wire if w.direction == "in"]
    peak = 30521
    for frame in reads:
        start, count = int.from_bytes(frame[2:4], "big"), int.from_bytes(frame[4:6], "big")
        assert not start <= peak < start + count or frame[1] != 4


def test_fields_missing_from_the_irnet_data_structure_are_reported_not_failed(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", options=["net-irnet-pro@1.variant=0"], tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json",
                       "net-irnet-pro@1", "uart_speed", "concentration"))
    assert recs[0]["field"] == "uart_speed" and recs[0]["value"] is None
    assert recs[0]["text"] == "not present (data structure 0)"
    assert isinstance(recs[1]["value"], float)


def test_on_a_newer_data_structure_the_same_field_is_read(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    recs = records(run("read", "-p", bus.port, *PATIENT, "--format", "json",
                       "net-irnet-pro@1", "uart_speed"))
    assert recs[0]["value"] is not None and recs[0]["value"].startswith("UART_")


# -- failures: one line each, distinct exit codes --------------------------------------


def test_unknown_field_or_profile_is_exit_2_with_a_hint() -> None:
    result = run("read", "-p", "/dev/null", "huiwen-aq@1", "co3")
    assert result.returncode == 2 and "has no field 'co3' (did you mean 'co2'?)" in result.stderr
    result = run("read", "-p", "/dev/null", "huiwen@1")
    assert result.returncode == 2 and "did you mean 'huiwen-aq'" in result.stderr
    result = run("read", "-p", "/dev/null", "huiwen-aq@1", "input:3")
    assert result.returncode == 2 and "add --raw" in result.stderr


def test_no_response_is_exit_4(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("read", "-p", bus.port, "--timeout", "0.3", "--retries", "0", "radar-level@9",
                 "level_cm")
    assert result.returncode == 4, (result.stdout + result.stderr)


def test_exception_reply_is_exit_5_and_named(sim: Sim) -> None:
    bus = sim("radar-level@1", tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "--raw", "1", "holding:0x0100")
    assert result.returncode == 5, (result.stdout + result.stderr)
    assert "ILLEGAL DATA ADDRESS" in result.stderr


def test_garbled_reply_is_exit_7(sim: Sim) -> None:
    bus = sim("radar-level@1", faults=["1:crc"], tick=None)
    result = run("read", "-p", bus.port, *PATIENT, "radar-level@1", "level_cm")
    assert result.returncode == 7, (result.stdout + result.stderr)


def test_missing_port_is_exit_3_one_line_no_traceback() -> None:
    proc = rtupoll("read", "-p", "/dev/ttyNOPE0", "huiwen-aq@1", "co2")
    assert proc.returncode == 3
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("rtupoll: ")
    assert "Traceback" not in proc.stderr and proc.stdout == ""
