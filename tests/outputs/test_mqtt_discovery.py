"""Home Assistant discovery on the broker (``outputs.mqtt_discovery``): which configs are
published, which cleared, and which of the broker's are this gateway's to clear.

On a real mosquitto: ``test_mqtt_cli.py`` (a reload, a device gone while rtupoll was
stopped) and ``test_mqtt_remove.py`` (``--mqtt-remove-discovery``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json

from rtupoll.config.mqtt_settings import parse_url
from rtupoll.config.site import from_specs
from rtupoll.outputs.mqtt_discovery import Discovery
from rtupoll.outputs.mqtt_outbox import Outbox
from rtupoll.outputs.mqtt_topics import device_topics


def drained(box: Outbox) -> dict[str, str]:
    out = {}
    while (item := box.pop()) is not None:
        out[item[0]] = item[1].payload
    return out


def test_a_device_that_left_has_its_config_cleared() -> None:
    async def main() -> None:
        settings = dataclasses.replace(parse_url("mqtt://broker.lan/plant"), gateway_id="gw1")
        both = from_specs("/dev/null", [("huiwen-aq", 3), ("radar-level", 4)])
        one = from_specs("/dev/null", [("huiwen-aq", 3)])
        discovery, box = Discovery(settings), Outbox()
        discovery.queue(box, both.devices(), device_topics(both))
        first = drained(box)
        gas = "homeassistant/device/rtupoll_gw1_radar-level_4/config"
        air = "homeassistant/device/rtupoll_gw1_huiwen-aq_3/config"
        assert {gas, air} <= set(first) and all(first.values())
        discovery.queue(box, one.devices(), device_topics(one))
        again = drained(box)
        assert again[gas] == "" and again[air] == first[air]  # cleared; the other kept
        # a config the broker still holds: ours and gone -> cleared; ours and here, or
        # another gateway's -> left alone
        assert discovery.check(box, gas, first[gas].encode()) == "rtupoll_gw1_radar-level_4"
        assert drained(box) == {gas: ""}
        assert discovery.check(box, air, first[air].encode()) is None
        theirs = json.dumps({**json.loads(first[gas]), "o": {"name": "zigbee2mqtt"}})
        assert discovery.check(box, gas, theirs.encode()) is None
        assert discovery.check(box, gas, b"{not json") is None
        assert discovery.check(box, gas, b"") is None
        assert len(box) == 0

    asyncio.run(main())


def test_controls_only_when_writes_are_allowed_and_not_once() -> None:
    site = from_specs("/dev/null", [("banner-ez-array", 5)], fields=["measurement_1_mode"])
    topics = device_topics(site)

    def components(**kw: object) -> dict[str, dict[str, object]]:
        settings = dataclasses.replace(parse_url("mqtt://broker.lan/plant"), allow_writes=True)
        configs = Discovery(settings, **kw).configs(site.devices(), topics)  # type: ignore[arg-type]
        (device,) = [json.loads(p) for t, p in configs.items() if "_bus_" not in t]
        return device["cmps"]  # type: ignore[no-any-return]

    assert any(c.get("p") == "select" for c in components().values())
    assert not any(c.get("p") == "select" for c in components(once=True).values())
