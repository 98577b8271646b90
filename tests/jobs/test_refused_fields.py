"""One register a device refuses no longer fails the whole device (issue 24 section 2):
an SDM120 whose firmware lacks total reactive energy (wire 0x0158-0x0159, in one block
with total active energy), simulated with a hole there. ``read`` prints every field
that answered and the refused one, exit 5; ``poll`` reports the rest ok, remembers the
field like a hole and reads it alone from then on."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from cli_runner import rtupoll

from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
REFUSED = "total_reactive_energy"


def requests(bus: SimulatedBus) -> list[str]:
    return [w.data[:6].hex(" ") for w in bus.wire if w.direction == "in"]


def test_read_prints_every_field_that_answered_and_the_refused_one_then_exits_5(
        sim: Sim) -> None:
    bus = sim("eastron-sdm120@10", faults=["10:hole=0x0158"], tick=None)
    result = rtupoll("read", "-p", bus.port, "-b", "2400", "--format", "json",
                     "eastron-sdm120@10")
    assert result.returncode == 5, result.stderr
    recs = {r["field"]: r for r in map(json.loads, result.stdout.splitlines())}
    assert recs[REFUSED]["value"] is None
    assert recs[REFUSED]["text"] == "refused: exception 02 ILLEGAL DATA ADDRESS"
    for name in ("voltage", "frequency", "total_active_energy"):
        assert recs[name]["value"] == bus.device(10).value(name).value, name
    assert all(r["value"] is not None for n, r in recs.items() if n != REFUSED)
    assert f"rtupoll: {REFUSED}: device 10 answered" in result.stderr
    # the block (refused), then its two halves: one reads, one is the refused field
    assert requests(bus)[-3:] == ["0a 04 01 56 00 04", "0a 04 01 56 00 02", "0a 04 01 58 00 02"]


def test_poll_reports_the_rest_ok_and_remembers_the_refused_field(
        sim: Sim, tmp_path: Path) -> None:
    bus = sim("eastron-sdm120@10", faults=["10:hole=0x0158"], tick=None)
    site = tmp_path / "site.yaml"
    site.write_text(f"buses:\n  - port: {bus.port}\n    baudrate: 2400\n    devices:\n"
                    "      - {name: meter, profile: eastron-sdm120, address: 10}\n")
    args = ["poll", "-c", str(site), "--remember-holes", "--once", "--format", "json"]
    first = rtupoll(*args)
    status = {r["field"]: r["status"] for r in map(json.loads, first.stdout.splitlines())}
    assert status.pop(REFUSED) == "exception"
    assert set(status.values()) == {"ok"} and "total_active_energy" in status
    kept = json.loads((tmp_path / "site.holes.json").read_text())["devices"]["meter"]
    assert kept["holes"] == [["input", 0x0158], ["input", 0x0159]]
    before = len(requests(bus))
    second = rtupoll(*args)
    assert "learned earlier" in second.stderr
    again = {r["field"]: r["status"] for r in map(json.loads, second.stdout.splitlines())}
    assert again == {**status, REFUSED: "exception"}
    later = requests(bus)[before:]
    assert "0a 04 01 56 00 04" not in later  # never bridged again
    assert "0a 04 01 58 00 02" in later and "0a 04 01 56 00 02" in later
