"""Commands from the broker, dispatched (``outputs.mqtt_dispatch``): which messages are
commands, one result for each, a retained one refused with one log line.

A command run on a simulated device over a real mosquitto is in ``test_mqtt_cli.py``
(and ``test_mqtt_get_holes.py``).
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from rtupoll.config.mqtt_settings import parse_url
from rtupoll.config.site import from_specs
from rtupoll.outputs.mqtt_dispatch import Commands
from rtupoll.outputs.mqtt_outbox import Outbox
from rtupoll.outputs.mqtt_state import StatePublisher
from rtupoll.outputs.mqtt_topics import device_topics


def test_commands_get_one_result_and_retained_ones_are_refused() -> None:
    async def main() -> tuple[dict[str, Any], list[str]]:
        site = from_specs("/dev/null", [("huiwen-aq", 3)])
        settings = parse_url("mqtt://broker.lan/plant")
        topics = device_topics(site)
        box, said = Outbox(), []
        commands = Commands(settings, StatePublisher(settings, topics), box,
                            lambda _level, msg, *args, **_kw: said.append(msg % args))
        commands.devices = {t: name for name, t in topics.items()}
        commands.take("plant/huiwen-aq_3/set", b'{"x": 1}', retain=True)
        commands.take("plant/huiwen-aq_3/get", b"", retain=True)
        commands.take("plant/nonesuch/get", b"", retain=False)  # no such device
        commands.take("plant/huiwen-aq_3/availability", b"online", retain=False)
        assert len(box) == 0 and len(said) == 1  # nothing runs; one line says why
        # the scheduler does not poll it (yet): still one result, with the CLI's words
        commands.take("plant/huiwen-aq_3/get", b"", retain=False)
        await asyncio.sleep(0)
        await commands.stop()
        got = box.pop()
        assert got is not None and got[0] == "plant/huiwen-aq_3/get/result"
        assert box.pop() is None
        return json.loads(got[1].payload), said

    result, said = asyncio.run(main())
    assert "ignoring the retained command on plant/huiwen-aq_3/set (and any other)" in said[0]
    assert "mosquitto_pub -r -n -t 'plant/huiwen-aq_3/set'" in said[0]
    assert result["status"] != "ok" and result["exit_code"] == 2
    assert result["error"] == "huiwen-aq@3 is not polled now (the site file was reloaded)"
