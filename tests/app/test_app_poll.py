"""One run of ``poll`` (``rtupoll.app.poll``) against a simulated bus on a pty: a
``PollRun`` in, the records written, an ``Outcome`` out (the CLI turns it into exit 9)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

from conftest import live_and_dead

from rtupoll.app.poll import Outcome, PollRun, record_format, run
from rtupoll.config.site import from_specs, load_site
from rtupoll.jobs.stats import Reading
from rtupoll.model.interpret import interpret
from rtupoll.outputs.influx import InfluxFormat
from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.records import CsvFormat, JsonFormat


def test_once_writes_the_records_and_names_each_failed_device(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:dead"])
    site = load_site(live_and_dead(tmp_path, bus.port))
    out = tmp_path / "readings.jsonl"
    said: list[str] = []
    outcome = run(PollRun(site, "test", fmt="json", once=True, output=out),
                  stop=asyncio.Event, say=said.append)
    assert (outcome.failed, outcome.total) == (1, 2)
    assert len(outcome.lines) == 1 and outcome.lines[0].startswith("radar-level@4: timeout: ")
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert {r["device"] for r in records if r["status"] == "ok"} == {"huiwen-aq@3"}
    dead = {r["status"] for r in records if r["device"] == "radar-level@4"}
    assert "timeout" in dead and dead <= {"timeout", "skipped"}  # the rest of its blocks
    assert not said  # a pty has no latency timer, no echo: nothing else to say


def test_a_silent_line_is_named_with_what_to_try(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("radar-level@4", faults=["4:dead"])
    site = from_specs(bus.port, [("radar-level", 4)], timeout=0.05, retries=0,
                      check_serial=False)
    outcome = run(PollRun(site, "test", fmt="csv", once=True, output=tmp_path / "r.csv"),
                  stop=asyncio.Event, say=lambda text: None)
    assert outcome.failed == 1
    assert outcome.lines[-1].startswith(f"nothing answered on {bus.port} at ")
    assert f"'rtupoll scan -p {bus.port}'" in outcome.lines[-1]
    assert (tmp_path / "r.csv").read_text().startswith("time,device,")


def test_all_answered_is_no_failure() -> None:
    assert Outcome() == Outcome(0, 0, [])


def test_the_format_by_its_name() -> None:
    site = from_specs("/dev/ttyUSB0", [("huiwen-aq", 3)], check_serial=False)
    assert isinstance(record_format("json", site), JsonFormat)
    assert isinstance(record_format("csv", site, header=False), CsvFormat)
    influx = record_format("influx", site)
    assert isinstance(influx, InfluxFormat)
    dev = site.buses[0].devices[0]
    co2 = dev.profile.field("co2")
    text = influx.text([Reading(1.0, dev, co2, interpret(co2, [500]))])
    assert {p for line in text.splitlines() for p in line.split(" ")[0].split(",")
            if p.startswith("bus=")} == {"bus=/dev/ttyUSB0"}  # the site's bus names
