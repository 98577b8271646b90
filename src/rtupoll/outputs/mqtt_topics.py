"""The site's device levels in the topic layout (``BASE/DEVICE/...``), checked."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rtupoll.errors import UsageError
from rtupoll.outputs.mqtt_state import topic_name

if TYPE_CHECKING:
    from rtupoll.config.site import Site

__all__ = ["device_topics"]


def device_topics(site: Site) -> dict[str, str]:
    """Every device's topic level by device name; refuses names that collide."""
    out: dict[str, str] = {}
    seen: dict[str, str] = {}
    for _bus, dev in site.devices():
        t = topic_name(dev.name)
        if t == "bridge":
            raise UsageError(f"device {dev.name!r}: 'bridge' is the gateway's own MQTT topic; "
                             "give the device another name")
        if t in seen:
            raise UsageError(f"devices {seen[t]!r} and {dev.name!r} would share the MQTT "
                             f"topic level {t!r}: rename one")
        seen[t], out[dev.name] = dev.name, t
    return out
