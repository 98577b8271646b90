"""``--format influx`` into a real InfluxDB 1.6 (``tests/influxdb.py`` starts it).

A multi-device site on the simulator, with faults, polled by the real CLI; every
line it wrote goes through InfluxDB's HTTP ``/write`` and must be accepted (204: a
type conflict refuses the whole line, which is how a whole device's data was lost),
and every device's fields must come back from ``/query``.
"""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from forked_cli import rtupoll_popen

from rtupoll.config.site import from_specs
from rtupoll.jobs.stats import Reading
from rtupoll.model.interpret import FieldValue
from rtupoll.outputs.influx import lines
from rtupoll.sim.runner import SimulatedBus
from tests.influxdb import Influx, influx_fixture  # noqa: F401
from tests.outputs.test_influx import parse_line

DEVICES = {1: "net-irnet-pro", 2: "radar-level", 3: "huiwen-aq", 5: "banner-ez-array",
           6: "xy-md02", 7: "eastron-sdm120"}
FAULTS = ["5:crc@30%", "2:exception@20%", "6:dead@12-", "3:slow=0.3@25%"]


def _site(tmp_path: Path, port: str) -> Path:
    site = tmp_path / "site.yaml"
    devices = "".join(f"      - {{name: {profile}-{a}, profile: {profile}, address: {a}, "
                      f"interval: 0.2, timeout: 0.15}}\n" for a, profile in DEVICES.items())
    site.write_text(f"buses:\n  - name: line1\n    port: {port}\n    baudrate: 9600\n"
                    f"    devices:\n{devices}", encoding="utf-8")
    return site


def _poll_until(site: Path, out: Path, tmp_path: Path,
                done: Callable[[list[str]], bool]) -> list[str]:
    err = (tmp_path / "stderr").open("w")
    proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "-c", str(site),
                             "--format", "influx", "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=err)
    try:
        deadline = time.monotonic() + 90  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline and proc.poll() is None:
            text = out.read_text() if out.exists() else ""
            if done(text.splitlines()):
                break
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    return out.read_text().splitlines()


def test_every_line_of_a_faulty_multi_device_site_is_accepted(
        sim: Callable[..., SimulatedBus], influx: Influx, tmp_path: Path) -> None:
    bus = sim(*(f"{p}@{a}" for a, p in DEVICES.items()), faults=FAULTS)
    bus.set(5, "error_code", "NONE")
    bus.set(1, "error", 64)  # an undocumented enum code: its number, and text saying so
    out = tmp_path / "readings.lp"

    def enough(got: list[str]) -> bool:
        cycles = [x for x in got if x.startswith("rtupoll_status,")]
        failed = [x for x in cycles if 'status="' in x]
        return len(cycles) >= 6 * 8 and len({x.split(",")[1] for x in failed}) >= 3

    text = _poll_until(_site(tmp_path, bus.port), out, tmp_path, enough)
    parsed = [parse_line(x) for x in text]
    readings = [p for p in parsed if p[0] == "rtupoll_reading"]
    statuses = [p for p in parsed if p[0] == "rtupoll_status"]
    assert len(statuses) >= 48 and len(readings) > len(statuses)
    # the faults did happen: failures of several kinds, and the dead device's timeouts
    kinds = {p[2].get("status") for p in statuses}
    assert {"timeout", "exception"} <= kinds, kinds

    influx.create("plant")
    # each line alone: a refused line names itself, and no line can hide behind another
    refused = [(line, influx.write("plant", [line])) for line in text]
    refused = [(line, got) for line, got in refused if got[0] != 204]
    assert not refused, f"{len(refused)} of {len(text)} lines refused, first: {refused[0]}"

    # one type per key: floats, and strings only under .text
    types = influx.field_types("plant", "rtupoll_reading")
    assert types and all(t == ("string" if k.endswith(".text") else "float")
                         for k, t in types.items()), types

    # every device's every field written is there, with as many points as lines carried it
    written: dict[str, dict[str, int]] = {}
    for _, tags, fields, _ in readings:
        per = written.setdefault(tags["device"], {})
        for k in fields:
            per[k] = per.get(k, 0) + 1
    assert set(written) == {f"{p}-{a}" for a, p in DEVICES.items()}
    for device, fields in written.items():
        rows = influx.query("plant", f'SELECT count(*) FROM "rtupoll_reading" '
                                     f"WHERE \"device\" = '{device}'")
        (series,) = rows
        counts = {c.removeprefix("count_"): v for c, v in
                  zip(series["columns"], series["values"][0], strict=True)
                  if c != "time" and v}
        assert counts == fields, device
    # what the issue saw lost, and the slow-interval energy, are all queryable
    huiwen = influx.query("plant", 'SELECT co2, pm25, tvoc, hcho, temperature, humidity '
                                   'FROM "rtupoll_reading" WHERE "profile" = \'huiwen-aq\'')
    assert huiwen and all(v is not None for v in huiwen[0]["values"][0])
    (irnet,) = influx.query("plant", 'SELECT "error", "error.text" FROM "rtupoll_reading" '
                                     "WHERE \"profile\" = 'net-irnet-pro' LIMIT 1")
    assert irnet["values"][0][1:] == [64, "unknown (64)"]
    (banner,) = influx.query("plant", 'SELECT "error_code", "error_code.text" FROM '
                                      "\"rtupoll_reading\" WHERE \"profile\" = "
                                      "'banner-ez-array' LIMIT 1")
    assert banner["values"][0][1] == 0 and banner["values"][0][2] == "NONE"  # a float code
    (energy,) = influx.query("plant", 'SELECT import_active_energy FROM "rtupoll_reading" '
                                      "WHERE \"profile\" = 'eastron-sdm120'")
    assert energy["values"][0][1] > 0
    # the status measurement: one point per device cycle, state always present
    (status,) = influx.query("plant", 'SELECT count("state"), count("up") FROM '
                                      '"rtupoll_status"')
    assert status["values"][0][1:] == [len(statuses), len(statuses)]


def test_extreme_numbers_are_accepted_and_read_back(influx: Influx) -> None:
    site = from_specs("/dev/null", [("huiwen-aq", 3)], check_serial=False)
    dev = dataclasses.replace(site.buses[0].devices[0], name="edge")
    p = dev.profile
    values = {"co2": 2**64 - 1, "temperature": -1e-7, "humidity": 1e20, "pm25": True,
              "tvoc": 0, "hcho": -(2**63)}
    readings = [Reading(1_700_000_000.5, dev, p.field(k), FieldValue(p.field(k), v, (0,)))
                for k, v in values.items()]
    got = lines(readings, bus="b", state="online")
    influx.create("edge")
    assert influx.write("edge", got) == (204, "")
    (series,) = influx.query("edge", 'SELECT * FROM "rtupoll_reading"')
    row = dict(zip(series["columns"], series["values"][0], strict=True))
    assert row["time"] == 1_700_000_000_500_000_000
    for k, v in values.items():
        assert float(row[k]) == float(v), k  # JSON writes 22.0 as 22
