"""An adapter pulled out and plugged in again under ``poll --mqtt``: the real CLI, a real
mosquitto, the simulator on a pty behind a link (the port's name), stopped and started.

The SDM120's energy totals are on ``interval: 60``. While the port is gone every field
is null and the status says so; when it is back, the first state message with readings
has the totals again (they were null for up to a minute, each message saying "ok"), and
no message ever says ``ok`` while a field is null.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.outputs.test_mqtt_cli import Poll, polls_fixture  # noqa: F401

SLOW = ("import_active_energy", "export_active_energy", "total_active_energy")
SITE = """\
buses:
  - name: line
    port: {port}
    baudrate: 2400
    devices:
      - {{name: meter, profile: eastron-sdm120, address: 7, interval: 0.2}}
mqtt:
  url: {url}/site
  gateway_id: g
"""


def test_slow_fields_have_values_in_the_first_state_after_the_port_is_back(
        broker: Broker, sim: Callable[..., SimulatedBus], polls: Callable[..., Poll],
        tmp_path: Path) -> None:
    link = tmp_path / "ttyUSB0"
    first = sim("eastron-sdm120@7", link=str(link))
    site = tmp_path / "site.yaml"
    site.write_text(SITE.format(port=link, url=broker.url))
    sub = broker.subscribe("site/meter")
    p = polls("-c", str(site), "--format", "json", "-o", str(tmp_path / "out.jsonl"))

    def state(check: Callable[[dict[str, Any]], bool]) -> Callable[[Any], bool]:
        return lambda m: m.topic == "site/meter" and bool(m.payload) and \
            check(json.loads(m.payload))

    def status(s: dict[str, Any]) -> str:
        return str(s["_rtupoll"]["status"])

    sub.wait(state(lambda s: status(s) == "ok" and s[SLOW[0]] is not None))
    first.stop()  # the adapter is pulled out
    gone = sub.wait(state(lambda s: s["_rtupoll"]["error"] is not None
                          and s["_rtupoll"]["error"].startswith("port: ")))
    assert all(json.loads(gone.payload)[n] is None for n in SLOW)
    after = len(sub.messages)
    sim("eastron-sdm120@7", link=str(link))  # ... and plugged in again
    back = sub.wait(state(lambda s: s["voltage"] is not None), after=after)
    s = json.loads(back.payload)
    assert all(s[n] is not None for n in SLOW), s  # read in the first cycle back
    assert status(s) == "ok", s
    assert p.stop() == 0, p.stderr
    for m in sub.on("site/meter"):
        if m.payload:
            s = json.loads(m.payload)
            nulls = [k for k, v in s.items() if v is None and k != "last_seen"]
            assert status(s) != "ok" or not nulls, (nulls, s)
