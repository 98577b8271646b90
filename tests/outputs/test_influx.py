"""``--format influx``: InfluxDB line protocol, parsed back with a strict parser.

The parser below follows the line-protocol reference: measurement escapes ``,`` and
space; tag keys, tag values and field keys escape ``,``, ``=`` and space; string
field values are double-quoted with ``"`` and ``\\`` escaped; integers end in ``i``;
the timestamp is an integer. Anything else is a ``ValueError``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_runner import Ran, rtupoll
from conftest import live_and_dead

from rtupoll.config.site import BusConfig, Site, from_specs
from rtupoll.jobs.stats import Reading
from rtupoll.model.interpret import FieldValue, interpret
from rtupoll.outputs.influx import InfluxFormat, lines
from rtupoll.sim.runner import SimulatedBus

Line = tuple[str, dict[str, str], dict[str, Any], int]


def _unescape_until(text: str, i: int, stops: str, escapable: str) -> tuple[str, int]:
    out = []
    while i < len(text) and text[i] not in stops:
        if text[i] == "\\" and i + 1 < len(text) and text[i + 1] in escapable:
            out.append(text[i + 1])
            i += 2
            continue
        out.append(text[i])
        i += 1
    return "".join(out), i


def parse_line(text: str) -> Line:
    if "\n" in text or not text:
        raise ValueError("one non-empty line")
    name, i = _unescape_until(text, 0, ", ", ", ")
    if not name:
        raise ValueError("no measurement")
    tags: dict[str, str] = {}
    while text[i] == ",":
        k, i = _unescape_until(text, i + 1, "=, ", ",= ")
        if text[i] != "=":
            raise ValueError(f"tag {k!r} without '='")
        v, i = _unescape_until(text, i + 1, ", ", ",= ")
        if not k or not v:
            raise ValueError("empty tag key or value")
        tags[k] = v
    if text[i] != " ":
        raise ValueError("no space before the fields")
    i += 1
    fields: dict[str, Any] = {}
    while True:
        k, i = _unescape_until(text, i, "=, ", ",= ")
        if not k or text[i] != "=":
            raise ValueError(f"bad field key at {i}")
        i += 1
        if text[i] == '"':
            i += 1
            out = []
            while text[i] != '"':
                if text[i] == "\\" and text[i + 1] in '"\\':
                    out.append(text[i + 1])
                    i += 2
                    continue
                out.append(text[i])
                i += 1
            fields[k] = "".join(out)
            i += 1
        else:
            j = i
            while j < len(text) and text[j] not in ", ":
                j += 1
            raw, i = text[i:j], j
            if raw.endswith("i"):
                fields[k] = int(raw[:-1])
            elif raw in ("true", "false"):
                fields[k] = raw == "true"
            else:
                value = float(raw)
                if value != value or value in (float("inf"), float("-inf")):
                    raise ValueError("NaN/inf is not line protocol")
                fields[k] = value
        if i < len(text) and text[i] == ",":
            i += 1
            continue
        break
    if text[i:i + 1] != " " or not text[i + 1:].isdigit():
        raise ValueError("no integer timestamp")
    return name, tags, fields, int(text[i + 1:])


def test_the_parser_is_strict() -> None:
    assert parse_line('m,a=b\\ c x=1i,y="q\\"" 5') == ("m", {"a": "b c"}, {"x": 1, "y": 'q"'}, 5)
    for bad in ("m x=1", "m,a= x=1 5", "m x=NaN 5", "m x=1 five", 'm x="open 5'):
        with pytest.raises((ValueError, IndexError)):
            parse_line(bad)


def _device(name: str) -> Any:
    site = from_specs("/dev/null", [("huiwen-aq", 3)], check_serial=False)
    return dataclasses.replace(site.buses[0].devices[0], name=name)


def test_escaping_of_tags_fields_and_strings_round_trips() -> None:
    dev = _device('air, "north" = 1\\')
    p = dev.profile
    co2 = interpret(p.field("co2"), [1175])
    level = interpret(p.field("co2_level"), [1])
    temp = FieldValue(p.field("temperature"), -4.5, (0,))
    nan = FieldValue(p.field("humidity"), float("nan"), (0,))
    text = FieldValue(p.field("pm25"), 'say "hi"\\ there,\nnow', (0,))
    t = 1_700_000_000.123
    readings = [Reading(t, dev, fv.field, fv) for fv in (co2, level, temp, nan, text)]
    readings.append(Reading(t + 0.5, dev, p.field("tvoc"), None, "timeout", 'no reply, "x"'))
    out = lines(readings, bus="line 1,a=b", state="online")
    parsed = [parse_line(x) for x in out]
    assert [m for m, *_ in parsed] == ["rtupoll_reading", "rtupoll_status"]
    _, tags, fields, ts = parsed[0]
    assert tags == {"address": "3", "bus": "line 1,a=b", "device": 'air, "north" = 1',
                    "profile": "huiwen-aq"}
    assert fields == {"co2": 1175.0, "co2_level": 1.0, "co2_level.text": "GOOD",
                      "temperature": -4.5, "pm25.text": 'say "hi"\\ there, now'}
    # one type per key, whatever the profile decodes: a float, or a string under .text
    assert all(isinstance(v, str) if k.endswith(".text") else isinstance(v, float)
               for k, v in fields.items())
    assert "humidity" not in fields  # NaN: no value at all, never a bare NaN
    assert ts == 1_700_000_000_123_000_000
    _, stags, status, sts = parsed[1]
    assert stags == tags and sts == 1_700_000_000_623_000_000
    assert status == {"up": 1, "ok": 5, "failed": 1, "state": "online", "status": "timeout",
                      "error": 'no reply, "x"'}


def poll(*args: str) -> Ran:
    return rtupoll("poll", *args)


def test_once_with_a_dead_device(sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3", "radar-level@4", faults=["4:dead"])
    bus.set(3, "co2", 777)
    bus.set(3, "temperature", -3)
    site = live_and_dead(tmp_path, bus.port)  # the dead one asked with a short timeout
    before = time.time_ns()
    out = tmp_path / "readings.lp"
    result = poll("-c", str(site), "--once", "--format", "influx", "-o", str(out))
    after = time.time_ns()
    assert result.returncode == 9, result.stderr
    text = out.read_text()
    assert text.endswith("\n")
    parsed = [parse_line(x) for x in text.splitlines()]
    data = [p for p in parsed if p[0] == "rtupoll_reading"]
    status = {p[1]["device"]: p[2] for p in parsed if p[0] == "rtupoll_status"}
    assert {p[1]["device"] for p in data} == {"huiwen-aq@3"}  # nothing from the dead one
    merged = {k: v for p in data for k, v in p[2].items()}
    assert merged["co2"] == 777 and merged["temperature"] == -3
    assert len([k for k in merged if not k.endswith(".text")]) == 15
    assert all(isinstance(v, float) for k, v in merged.items() if not k.endswith(".text"))
    assert all(before <= p[3] <= after for p in parsed)
    assert all(p[1]["bus"] == bus.port for p in parsed)
    assert status["huiwen-aq@3"]["up"] == 1 and status["radar-level@4"]["up"] == 0
    assert status["radar-level@4"]["status"] == "timeout"
    # --once writes each device's state as the service does (docs/service.md's example)
    assert status["huiwen-aq@3"]["state"] == "online"
    assert status["radar-level@4"]["state"] in ("retrying", "offline", "starting")

    again = poll("-c", str(site), "--once", "--format", "influx", "-o", str(out))
    assert again.returncode == 9
    assert out.read_text().startswith(text)  # appended, not overwritten


def test_formatter_splits_several_devices_and_keeps_state() -> None:
    a, b = _device("a"), _device("b")
    ra = Reading(1.0, a, a.profile.field("co2"), interpret(a.profile.field("co2"), [5]))
    rb = Reading(2.0, b, b.profile.field("co2"), None, "garbled", "bad CRC")
    site = Site((BusConfig("one", "/dev/a", 9600, devices=(a,)),
                 BusConfig("two", "/dev/b", 9600, devices=(b,))))
    text = InfluxFormat(site).text([ra, rb], "online")
    parsed = [parse_line(x) for x in text.splitlines()]
    assert [(m, t["device"], t["bus"]) for m, t, _, _ in parsed] == [
        ("rtupoll_reading", "a", "one"), ("rtupoll_status", "a", "one"),
        ("rtupoll_status", "b", "two")]
    assert parsed[2][2]["up"] == 0 and parsed[2][2]["error"] == "bad CRC"


def test_the_bus_tag_follows_the_site_it_is_given_and_no_other() -> None:
    """The format owns its device -> bus names: a reload hands it the new site
    (``follow``); the site it was built from, or a dict anyone holds, changes nothing."""
    a = _device("a")
    ra = Reading(1.0, a, a.profile.field("co2"), interpret(a.profile.field("co2"), [5]))
    fmt = InfluxFormat(Site((BusConfig("one", "/dev/a", 9600, devices=(a,)),)))
    assert {parse_line(x)[1]["bus"] for x in fmt.text([ra]).splitlines()} == {"one"}
    fmt.follow(Site((BusConfig("moved", "/dev/b", 9600, devices=(a,)),)))
    assert {parse_line(x)[1]["bus"] for x in fmt.text([ra]).splitlines()} == {"moved"}
    fmt.follow(Site(()))  # gone from the site: no bus tag (an empty tag is invalid)
    assert all("bus" not in parse_line(x)[1] for x in fmt.text([ra]).splitlines())
