"""The devices' topic levels (``outputs.mqtt_topics``): safe, distinct, not ``bridge``."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.site import from_specs, load_site
from rtupoll.errors import UsageError
from rtupoll.outputs.mqtt_state import topic_name
from rtupoll.outputs.mqtt_topics import device_topics


def site_file(tmp_path: Path, *names: str) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text("buses:\n  - name: plant\n    port: tcp://127.0.0.1:5020\n"
                    "    devices:\n" + "".join(
                        f"      - {{name: {n}, profile: radar-level, address: {i}}}\n"
                        for i, n in enumerate(names, 1)))
    return path


def test_topic_names_are_safe_and_distinct() -> None:
    assert topic_name("radar-level@4") == "radar-level_4"
    assert topic_name("tank 1/north") == "tank_1_north"
    site = from_specs("/dev/null", [("huiwen-aq", 3), ("radar-level", 4)])
    assert device_topics(site) == {"huiwen-aq@3": "huiwen-aq_3", "radar-level@4": "radar-level_4"}


def test_topic_collisions_are_refused(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="'tank 4' and 'tank_4' would share"):
        device_topics(load_site(site_file(tmp_path, "tank 4", "tank_4")))


def test_the_bridge_level_is_the_gateways_own(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="'bridge' is the gateway's own MQTT topic"):
        device_topics(load_site(site_file(tmp_path, "bridge")))
