"""Home Assistant discovery on the broker: publishing this gateway's configs, removing
those of devices that left, and ``--mqtt-remove-discovery``.

What a config says is ``homeassistant`` (pure); this room keeps which configs were
published, so that a device no longer in the site has its config cleared, whether it
left on a reload or while rtupoll was not running (the broker's retained copy is ours:
``homeassistant.is_ours``).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from rtupoll.errors import BrokerError
from rtupoll.outputs import homeassistant as ha
from rtupoll.outputs import mqtt_commands as cmd
from rtupoll.outputs.mqtt_client import aiomqtt_module, close, connect, describe, make_client
from rtupoll.outputs.mqtt_client import retained as retained_now
from rtupoll.outputs.mqtt_state import topic_name
from rtupoll.outputs.mqtt_topics import device_topics
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.config.mqtt_settings import MqttSettings
    from rtupoll.config.site import BusConfig, DeviceConfig, Site
    from rtupoll.outputs.mqtt_outbox import Outbox

__all__ = ["Discovery", "Removed", "remove_discovery"]

Devices = Iterable[tuple["BusConfig", "DeviceConfig"]]


class Discovery:
    """The discovery configs this gateway has published (object id -> config topic)."""

    def __init__(self, settings: MqttSettings, *, once: bool = False) -> None:
        self.settings = settings
        self.once = once  # poll --once takes no commands: no controls
        self._published: dict[str, str] = {}

    def configs(self, devices: Devices, topics: dict[str, str]) -> dict[str, str]:
        """Every discovery message of ``devices`` (and their buses), by config topic;
        these are now the ones published."""
        s, gid = self.settings, self.settings.gateway_id
        devices = list(devices)
        out: dict[str, str] = {}
        self._published.clear()
        for bus, dev in devices:
            t = topics.get(dev.name) or topic_name(dev.name)
            opts = s.options(dev.name)
            controls = {f.name: s.allow_writes and not self.once and (
                not cmd.protected(dev.profile, f) or f.name in opts.allow)
                for f in dev.fields if f.writable}
            oid = ha.object_id(gid, t)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.device_config(dev, bus, gateway_id=gid, base=s.base,
                                                  topic=t, controls=controls, qos=s.qos))
            self._published[oid] = topic
        for bus in {bus.name: bus for bus, _ in devices}.values():
            oid = ha.bus_object_id(gid, bus.name)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.bus_config(bus, gateway_id=gid, base=s.base, qos=s.qos))
            self._published[oid] = topic
        return out

    def queue(self, outbox: Outbox, devices: Devices, topics: dict[str, str]) -> None:
        """Every config of ``devices`` into the outbox; those published before for
        devices no longer among them cleared."""
        before = dict(self._published)
        qos = self.settings.qos
        for topic, payload in self.configs(devices, topics).items():
            outbox.put(topic, payload, retain=True, qos=qos)
        for oid, topic in before.items():
            if oid not in self._published:
                outbox.put(topic, "", retain=True, qos=qos)

    def check(self, outbox: Outbox, topic: str, payload: bytes) -> str | None:
        """A config the broker holds: if it is ours, of a device no longer in the site,
        clear it; the object id cleared, or None."""
        oid = topic.split("/")[-2]
        if not payload or oid in self._published:
            return None
        if not _ours(payload, self.settings):
            return None
        outbox.put(topic, "", retain=True, qos=self.settings.qos)
        return oid


@dataclass(frozen=True)
class Removed:
    """What ``--mqtt-remove-discovery`` cleared: Home Assistant configs, and this gateway's
    other retained topics (bridge state and info, availability, retained states)."""

    configs: tuple[str, ...]
    topics: tuple[str, ...]


async def remove_discovery(settings: MqttSettings, site: Site) -> Removed:
    """``--mqtt-remove-discovery``: of what the broker holds retained, clear every Home
    Assistant config of this gateway (the site's devices and buses, and any other it
    published before: ``homeassistant.is_ours``), then under the base topic every topic
    of this gateway's layout: ``bridge/info``, each device's level (``availability``, a
    retained state, field topics) and ``bridge/state`` last. A topic the broker does not
    hold is not touched (an empty message there would make Home Assistant log a warning),
    and nothing else under the base is."""
    lib = aiomqtt_module()
    s = settings
    client = make_client(s, will=False)
    await connect(client, s)
    base = s.base
    try:
        topics_of = device_topics(site)
        site_configs = set(Discovery(s).configs(site.devices(), topics_of))
        held = await retained_now(client, base, [f"{s.discovery_prefix}/device/+/config",
                                                 f"{base}/#"])
        configs = [t for t, body in held.items()
                   if t.startswith(f"{s.discovery_prefix}/device/")
                   and (t in site_configs or _ours(body, s))]
        info, state = f"{base}/bridge/info", f"{base}/bridge/state"
        levels = set(topics_of.values()) | _info_levels(held.get(info, b""))
        levels |= {t[len(base) + 1:-len("/availability")] for t in held
                   if t.startswith(f"{base}/") and t.endswith("/availability")}
        levels.discard("bridge")
        mine = [t for t in held if t.startswith(f"{base}/")
                and t[len(base) + 1:].split("/")[0] in levels]
        topics = [*sorted(mine), *(t for t in (info, state) if t in held)]
        for topic in [*configs, *topics]:
            await client.publish(topic, b"", qos=1, retain=True)
    except lib.MqttError as exc:
        raise BrokerError(f"{s.where}: {describe(exc, s)}") from None
    finally:
        await close(client)
    return Removed(tuple(configs), tuple(topics))


def _ours(body: bytes, s: MqttSettings) -> bool:
    with contextlib.suppress(ValueError, RecursionError):
        obj = json.loads(body)
        return isinstance(obj, dict) and ha.is_ours(obj, s.gateway_id, s.base)
    return False


def _info_levels(body: bytes) -> set[str]:
    """The device levels a retained ``bridge/info`` names (its ``devices`` keys)."""
    with contextlib.suppress(ValueError, RecursionError, AttributeError):
        devices = json.loads(body or b"{}").get("devices", {})
        if isinstance(devices, dict):
            return {str(k) for k in devices}
    return set()
