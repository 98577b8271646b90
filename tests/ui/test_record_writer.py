"""``poll``'s record writer (``rtupoll.ui.record_writer``): whole batches, a file reopened
at its path (SIGHUP after logrotate), the CSV header where a file starts, the format
following a reloaded site."""

from __future__ import annotations

import io
import json
from pathlib import Path

from rtupoll.config.site import BusConfig, DeviceConfig, Site, from_specs
from rtupoll.jobs.stats import Reading
from rtupoll.model.interpret import interpret
from rtupoll.outputs.influx import InfluxFormat
from rtupoll.ui.outfile import OutputFile
from rtupoll.ui.record_writer import RecordWriter
from rtupoll.ui.records import CsvFormat, JsonFormat, reading_record, to_json


def _device() -> DeviceConfig:
    return from_specs("/dev/null", [("huiwen-aq", 3)], check_serial=False).buses[0].devices[0]


def _reading(dev: DeviceConfig, co2: int = 500) -> Reading:
    field = dev.profile.field("co2")
    return Reading(1.0, dev, field, interpret(field, [co2]))


def test_reopen_starts_a_csv_file_with_its_header(tmp_path: Path) -> None:
    reading = _reading(_device())
    path = tmp_path / "readings.csv"
    with path.open("a", encoding="utf-8", newline="") as fh:
        writer = RecordWriter(fh, CsvFormat(header=True), path=path)
        writer.write([reading])
        path.rename(tmp_path / "readings.csv.1")
        writer.reopen()
        writer.write([reading, reading])
        writer.out.close()
    old, new = (tmp_path / "readings.csv.1").read_text(), path.read_text()
    assert old.splitlines()[0].startswith("time,device,") and len(old.splitlines()) == 2
    assert new.splitlines()[0] == old.splitlines()[0] and len(new.splitlines()) == 3


def test_a_reopened_file_that_has_records_gets_no_second_header(tmp_path: Path) -> None:
    reading = _reading(_device())
    path = tmp_path / "readings.csv"
    out = OutputFile(path)
    try:
        writer = RecordWriter(out, CsvFormat(header=out.fresh), path=path)
        writer.write([reading])
        writer.reopen()  # the same file (nobody moved it): it has its header
        writer.write([reading])
    finally:
        out.close()
    lines = path.read_text().splitlines()
    assert len(lines) == 3 and sum(line.startswith("time,") for line in lines) == 1


def test_json_lines_are_the_records_and_stdout_is_never_reopened() -> None:
    dev = _device()
    out = io.StringIO()
    writer = RecordWriter(out, JsonFormat())
    writer.write([_reading(dev, 500), _reading(dev, 501)])
    writer.reopen()  # no path: the stream goes on
    writer.write([])  # nothing: nothing written
    writer.write([_reading(dev, 502)])
    lines = out.getvalue().splitlines()
    assert [json.loads(line)["value"] for line in lines] == [500, 501, 502]
    assert lines[0] == to_json(reading_record(_reading(dev, 500)))


def test_follow_hands_the_reloaded_site_to_the_format() -> None:
    dev = _device()
    out = io.StringIO()
    writer = RecordWriter(out, InfluxFormat(Site((BusConfig("a", "/dev/a", 9600,
                                                             devices=(dev,)),))))
    writer.write([_reading(dev)])
    writer.follow(Site((BusConfig("b", "/dev/b", 9600, devices=(dev,)),)))
    writer.write([_reading(dev)])
    tags = [line.split(" ")[0] for line in out.getvalue().splitlines()]
    assert any("bus=a" in t for t in tags[:2]) and all("bus=b" in t for t in tags[2:])
    assert all("bus=a" not in t for t in tags[2:])
