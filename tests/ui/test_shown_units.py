"""One reading, one number and unit for people: the live table, ``read``'s table, the
dashboard and ``/api/state`` all show the IRNET's kelvin as °C (``model.interpret``'s one
rule); the records (``--format json``, MQTT, InfluxDB) keep the profile's unit, and say
it. A difference in kelvin is the same number in °C.
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Callable
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.model.interpret import display_value, field_words, interpret
from rtupoll.sim.runner import SimulatedBus
from rtupoll.ui.live import PollView
from rtupoll.web.state import poll_state
from tests.ui.test_live import scanned, show
from tests.web_helpers import devices, field, get_json, running, until

KELVIN = 296.67  # 23.52 °C


def test_the_rule_kelvin_as_celsius_at_the_fields_decimals() -> None:
    f = load_one("net-irnet-pro", []).field("temperature")
    fv = interpret(f, field_words(f, KELVIN))
    assert fv.value == KELVIN and f.unit == "K"
    assert display_value(fv) == (23.52, "23.52", "°C")
    assert display_value(fv, celsius=False) == (KELVIN, "296.67", "K")
    offset = dataclasses.replace(f, name="temperature_offset")  # a difference: no 273.15
    assert display_value(interpret(offset, field_words(offset, 1.5))) == (1.5, "1.50", "°C")


def test_the_live_table_and_the_dashboards_state_agree(
        sim: Callable[..., SimulatedBus]) -> None:
    """One scheduler, as in one ``poll --simulate --http`` process: the live table and
    the state the dashboard and ``/api/state`` are made of."""
    bus = sim("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
              "banner-ez-array@5")
    bus.set(1, "temperature", KELVIN)
    scheduler = scanned(bus)
    irnet = next(line for line in show(PollView(scheduler.buses, title="t"), 160, 60)
                 if line.startswith("net-irnet-pro@1"))
    assert re.search(r"temperature\s*│\s*23\.52\s*│\s*°C\s*│", irnet), irnet
    temperature = field(devices(poll_state(scheduler, title="t"))["net-irnet-pro@1"],
                        "temperature")
    assert (temperature["value"], temperature["text"], temperature["unit"]) == \
        (23.52, "23.52", "°C")


def test_read_and_the_dashboard_show_it_so_and_the_records_keep_kelvin(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("net-irnet-pro@1")
    bus.set(1, "temperature", KELVIN)
    table = rtupoll("read", "-p", bus.port, "-b", "9600", "net-irnet-pro@1", "temperature")
    assert table.returncode == 0, table.stderr
    row = next(line for line in table.stdout.splitlines() if "temperature" in line)
    assert "23.52" in row and "°C" in row and "296" not in row
    records = rtupoll("read", "-p", bus.port, "-b", "9600", "--format", "json",
                      "net-irnet-pro@1", "temperature")
    rec = json.loads(records.stdout)
    assert (rec["value"], rec["unit"]) == (KELVIN, "K")  # the profile's unit, said
    with running(["poll", "--format", "json", "--interval", "0.2", "-p", bus.port, "-b",
                  "9600", "--http", "127.0.0.1:0", "net-irnet-pro@1"], tmp_path) as p:

        def read() -> dict[str, object] | None:
            f = field(devices(get_json(p.url + "api/state"))["net-irnet-pro@1"],
                      "temperature")
            return f if f["status"] == "ok" else None

        got = until(read, "the temperature read")
        assert (got["value"], got["text"], got["unit"]) == (23.52, "23.52", "°C")
        trend = until(lambda: get_json(p.url + "api/trend?device=net-irnet-pro%401"
                                       "&field=temperature") or None, "a trend")
        assert trend["v"] and all(abs(v - 23.52) < 0.01 for v in trend["v"])


def test_decode_shows_it_so_too_and_its_records_keep_kelvin() -> None:
    """``decode --profile``: the line a person reads in °C, the JSON record in K."""
    from rtupoll.rtu.crc import with_crc

    words = field_words(load_one("net-irnet-pro", []).field("temperature"), KELVIN)
    reply = with_crc(bytes([1, 4, 4]) + b"".join(w.to_bytes(2, "big") for w in words))
    request = with_crc(bytes([1, 4, 0, 4, 0, 2]))
    text = rtupoll("decode", "--profile", "net-irnet-pro", request.hex(), reply.hex())
    assert text.returncode == 0, text.stderr
    assert "temperature (0x0004) = 23.52 °C" in text.stdout, text.stdout
    got = rtupoll("decode", "--profile", "net-irnet-pro", "--format", "json", request.hex(),
                  reply.hex())
    carried = [c for line in got.stdout.splitlines() for c in json.loads(line)["fields"]]
    assert [(c["value"], c["unit"]) for c in carried if c["value"] is not None] == [
        (KELVIN, "K")]
