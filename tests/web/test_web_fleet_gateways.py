"""The fleet page fed by real gateways: two ``rtupoll poll --mqtt`` processes with their
own identities on one real mosquitto, and ``rtupoll web --mqtt`` showing both.

The browser tests publish hand-made ``bridge/info`` messages; this one proves that what
a gateway really publishes (outputs/fleet.py) is what the fleet viewer (web/fleet.py)
reads: the devices' topic levels, their names, values and availability.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.web_helpers import Proc, gateway_and_fleet, get_json, running, until


def gateway(broker: Broker, bus: SimulatedBus, ident: str, tmp: Path) -> Proc:
    return Proc(["poll", "-p", bus.port, "-b", "9600", "--format", "json", "-o",
                 str(tmp / f"{ident}.jsonl"), "--mqtt", broker.url, "--mqtt-id", ident,
                 "huiwen-aq@3", "radar-level@2"], tmp, name=ident, fresh=True)


def test_two_real_gateways_show_on_one_fleet_page(broker: Broker,
                                                  sim: Callable[..., SimulatedBus],
                                                  tmp_path: Path) -> None:
    north = sim("huiwen-aq@3", "radar-level@2", tcp=True, tick=None)
    south = sim("huiwen-aq@3", "radar-level@2", tcp=True, tick=None, faults=["2:dead"])
    north.set(3, "co2", 612)
    south.set(3, "co2", 1480)
    gateways = [gateway(broker, north, "north", tmp_path),
                gateway(broker, south, "south", tmp_path)]
    try:
        with running(["web", "--mqtt", broker.url, "--http", "127.0.0.1:0"], tmp_path,
                     name="web", fresh=True) as web:

            def both() -> dict[str, Any] | None:
                state = get_json(web.url + "api/state")
                shown = {(gw["id"], d["name"]): d
                         for gw in state["gateways"] for b in gw["buses"]
                         for d in b["devices"]}
                co2 = {k: next((f.get("value") for f in d["fields"] if f["name"] == "co2"),
                               None) for k, d in shown.items()}
                ready = len(shown) == 4 and all(v is not None for k, v in co2.items()
                                                if k[1] == "huiwen-aq@3")
                return {"shown": shown, "co2": co2} if ready else None

            got = until(both, "both gateways' devices with values on the fleet page",
                        limit=90)
            names = {name for _, name in got["shown"]}
            assert names == {"huiwen-aq@3", "radar-level@2"}  # the site's names, not topics
            values = sorted(v for (_, name), v in got["co2"].items() if name == "huiwen-aq@3")
            assert values == [612, 1480]  # each building's own, never mixed

            def dead_shown() -> bool:
                state = get_json(web.url + "api/state")
                states = {d["state"] for gw in state["gateways"] for b in gw["buses"]
                          for d in b["devices"] if d["name"] == "radar-level@2"}
                return "online" in states and states != {"online"}

            until(dead_shown, "the south radar not online, the north one online", limit=90)
    finally:
        for g in gateways:
            g.stop()
    for g in gateways:
        assert "Traceback" not in g.stderr(), g.stderr()


def test_a_gateways_own_dashboard_names_it_as_the_fleet_page_does(
        broker: Broker, sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    """``--mqtt-id``: the id the gateway publishes under is its dashboard's too (the host
    name's id otherwise, which the fleet page would not know it by)."""
    bus = sim("huiwen-aq@3", tcp=True, tick=None)
    with gateway_and_fleet(broker.url, bus.port, "huiwen-aq@3", tmp_path) as (east, web):
        fleet = until(lambda: [gw["id"] for gw in get_json(web.url + "api/state")["gateways"]]
                      or None, "the gateway on the fleet page", limit=90)
        own = [gw["id"] for gw in get_json(east.url + "api/state")["gateways"]]
        assert own == fleet == ["east"]
