"""``rtupoll poll --mqtt URL``: readings to an MQTT broker, commands back, Home Assistant.

A service (``rtupoll.jobs.services``) beside the scheduler, in Zigbee2MQTT's layout:

    BASE/DEVICE                 {"co2": 1175, ..., "last_seen": "...", "_rtupoll": {...}}
    BASE/DEVICE/availability    online | offline   (retained; offline while backed off)
    BASE/bridge/state           online | offline   (retained; the last will, and a clean stop)
    BASE/bridge/info            who this gateway is, its devices and fields (retained)
    BASE/DEVICE/FIELD           plain values, when field_topics is on
    BASE/DEVICE/set[/result]    writes (``outputs.mqtt_commands``)
    BASE/DEVICE/get[/result]    reads now, ahead of the schedule

DEVICE is the device's name with every character other than letters, digits, ``_``,
``-`` and ``.`` replaced by ``_`` (``radar-level@4`` -> ``radar-level_4``). BASE is
``rtupoll/<gateway_id>`` unless given (``outputs.fleet``).

The rooms: ``mqtt_state`` turns readings into messages (pure), ``mqtt_topics`` names
the devices' levels, ``mqtt_outbox`` holds what waits for the broker and publishes it,
``mqtt_connection`` keeps the broker (reconnecting with backoff), ``mqtt_client`` is
the aiomqtt client and why a connection failed, ``homeassistant`` turns the site into
discovery (pure) and ``mqtt_discovery`` publishes and removes it, ``mqtt_dispatch``
runs commands (``mqtt_commands`` checks and applies them); ``ui.mqtt_footer`` is the
live table's line. This module is the service that joins them.

The broker never holds up polling: ``on_readings`` only puts the message in an
outbox that keeps the latest message per topic, and one task publishes from it.
When the broker goes away the outbox keeps filling (bounded: one message per
topic, so a device's intermediate states are dropped, its latest kept), the
connection is retried with backoff, and the operator gets one log line when the
broker goes and one when it is back; on reconnect the bridge state, discovery,
every device's availability and latest state are published again.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING

from rtupoll.config.mqtt_settings import MqttSettings
from rtupoll.errors import UsageError
from rtupoll.jobs.services import Follow, Service
from rtupoll.jobs.stats import State
from rtupoll.outputs.fleet import bridge_info, version
from rtupoll.outputs.mqtt_client import CONNECT_TIMEOUT, aiomqtt_module, describe
from rtupoll.outputs.mqtt_connection import Connection, backoff
from rtupoll.outputs.mqtt_discovery import Discovery, Removed, remove_discovery
from rtupoll.outputs.mqtt_dispatch import Commands
from rtupoll.outputs.mqtt_outbox import Outbox
from rtupoll.outputs.mqtt_state import Out, StatePublisher, plain, topic_name
from rtupoll.outputs.mqtt_topics import device_topics
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    import aiomqtt
    from rich.text import Text

    from rtupoll.config.site import BusConfig, DeviceConfig, Site
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.services import Reload
    from rtupoll.jobs.stats import Reading

__all__ = ["MqttService", "Outbox", "Removed", "backoff", "describe", "device_topics",
           "from_options", "plain", "remove_discovery", "remove_discovery_now",
           "topic_name"]

log = logging.getLogger("rtupoll.mqtt")
STOP_FLUSH = 5.0  # seconds a clean stop waits for the last messages to go out


class MqttService(Service):
    """The MQTT side of ``poll``: see the module docstring."""

    def __init__(self, settings: MqttSettings, site: Site, *, once: bool = False,
                 log_lines: bool = True) -> None:
        """``log_lines=False``: no log lines (under the live table ``footer`` says it)."""
        self.settings = settings
        self.log_lines = log_lines
        self.site = site
        self.once = once  # poll --once: publish one scan; take no commands
        self.topics = device_topics(site)
        self.publisher = StatePublisher(settings, self.topics)
        self.outbox = Outbox()
        self.connection = Connection(settings, self.outbox, self._log)
        self.discovery = Discovery(settings, once=once)
        self.commands = Commands(settings, self.publisher, self.outbox, self._log)
        self.commands.devices = {t: name for name, t in self.topics.items()}
        self._scheduler: Scheduler | None = None
        self._task: asyncio.Task[None] | None = None
        # device -> the fields its generation lacks, as announced (a variant learned)
        self._absent: dict[str, frozenset[str]] = {}

    @property
    def published(self) -> int:
        """Messages the broker took."""
        return self.outbox.published

    # -- the Service protocol ------------------------------------------------

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = self.commands.scheduler = scheduler
        client = await self.connection.open()
        self._log(logging.INFO, "mqtt: connected to %s as gateway %s, publishing under %s/",
                  self.settings.where, self.settings.gateway_id, self.settings.base)
        self._task = asyncio.create_task(self.connection.run(
            client, self._session, lambda: len(self.publisher.state)))
        # subscribed and announced; a session that broke at once goes on reconnecting
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self.connection.connected.wait(), CONNECT_TIMEOUT)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        for out in self.publisher.readings(dev.config, dev.stats.state is State.ONLINE,
                                           dev.stats.last_good_time, readings):
            self._put(out)
        absent = frozenset(f.name for f in dev.absent)
        if absent != self._absent.get(dev.config.name, frozenset()):
            # the device said which generation it is: announce it without the fields it
            # lacks (Home Assistant drops those entities, never unknown for ever)
            self._absent[dev.config.name] = absent
            self._announce()

    async def on_reload(self, site: Site) -> Reload:
        """Topics and discovery follow the new site once the scheduler has it."""
        def then(scheduler: Scheduler) -> list[str]:
            self._reloaded(scheduler.site)
            return []
        return Follow(then)

    async def stop(self) -> None:
        """Flush what is waiting, say offline (retained), disconnect cleanly."""
        await self.commands.stop()
        if self._task is None:
            return
        if self.connection.connected.is_set():
            qos = max(1, self.settings.qos)
            for out in self.publisher.offline():
                self._put(out, qos)
            self.outbox.put(self._bridge, "offline", retain=True, qos=qos)
            self.outbox.flushed.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self.outbox.flushed.wait(), STOP_FLUSH)
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)

    def footer(self) -> Text:
        """The live table's line (``ui.mqtt_footer``)."""
        from rtupoll.ui.mqtt_footer import line

        c = self.connection
        return line(f"{self.settings.where}/{self.settings.base}",
                    connected=c.connected.is_set(), error=c.last_error,
                    lost_for=None if c.lost_at is None else time.monotonic() - c.lost_at,
                    published=self.outbox.published, waiting=len(self.outbox))

    # -- one session ---------------------------------------------------------

    @property
    def _bridge(self) -> str:
        return f"{self.settings.base}/bridge/state"

    async def _session(self, client: aiomqtt.Client) -> None:
        """Subscribe, say online, queue everything the broker may have forgotten, then
        read the broker's messages and publish the outbox until either breaks."""
        s, base = self.settings, self.settings.base
        subs = [(f"{s.discovery_prefix}/status", s.qos)]
        if not self.once:
            subs += [(f"{base}/+/set", s.qos), (f"{base}/+/get", s.qos)]
        if s.discovery:
            subs.append((f"{s.discovery_prefix}/device/+/config", s.qos))
        await client.subscribe(subs)
        await client.publish(self._bridge, "online", qos=max(1, s.qos), retain=True)
        self._queue_info()
        self._queue_again()
        self.connection.connected.set()
        reader = asyncio.create_task(self._read(client))
        writer = asyncio.create_task(self.outbox.drain(client))
        try:
            done, _ = await asyncio.wait([reader, writer], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                task.result()
        finally:
            for task in (reader, writer):
                task.cancel()
            await asyncio.gather(reader, writer, return_exceptions=True)

    async def _read(self, client: aiomqtt.Client) -> None:
        """The broker's messages: Home Assistant's status, discovery configs, commands."""
        s, base = self.settings, self.settings.base
        status = f"{s.discovery_prefix}/status"
        configs = f"{s.discovery_prefix}/device/"
        async for message in client.messages:
            topic = message.topic.value
            payload = message.payload if isinstance(message.payload, bytes) else \
                str(message.payload if message.payload is not None else "").encode()
            if topic == status:
                if payload.strip() == b"online":  # Home Assistant (re)started
                    self._queue_again()
            elif topic.startswith(configs):
                oid = self.discovery.check(self.outbox, topic, payload)
                if oid is not None:
                    self._log(logging.INFO, "mqtt: removed the Home Assistant discovery of "
                              "%s (no longer in the site)", oid)
            elif topic.startswith(f"{base}/"):
                self.commands.take(topic, payload, retain=bool(message.retain))

    # -- what is published ---------------------------------------------------

    def _queue_again(self) -> None:
        """Discovery and every device's latest state (availability first), for a broker
        or a Home Assistant that may have forgotten them."""
        self._queue_discovery()
        for out in self.publisher.latest():
            self._put(out)

    def _announce(self) -> None:
        """What the gateway says about its devices (info, discovery), again: they changed."""
        if self.connection.connected.is_set():
            self._queue_info()
        self._queue_discovery()

    def _queue_info(self) -> None:
        """``BASE/bridge/info``: who this gateway is and what it polls (retained)."""
        info = bridge_info(self.settings.gateway_id, self.settings.base, self._devices(),
                           self.topics, version())
        self.outbox.put(f"{self.settings.base}/bridge/info", to_json(info), retain=True,
                        qos=max(1, self.settings.qos))

    def _queue_discovery(self) -> None:
        if self.settings.discovery:
            self.discovery.queue(self.outbox, self._devices(), self.topics)

    def _reloaded(self, site: Site) -> None:
        """The site file was reloaded (SIGHUP): topics and discovery follow it; a device
        that left has its retained availability cleared."""
        self.site = site
        try:
            topics = device_topics(site)
        except UsageError as exc:
            self._log(logging.ERROR, "mqtt: %s (keeping the old topics)", exc)
            return
        for name, t in self.topics.items():
            if name not in topics:
                for out in self.publisher.forget(t):
                    self._put(out)
        self.topics = self.publisher.topics = topics
        self.commands.devices = {t: name for name, t in topics.items()}
        self._announce()

    def _devices(self) -> Iterator[tuple[BusConfig, DeviceConfig]]:
        """The devices, each with the fields it has (those its generation lacks left
        out once it has said which it is)."""
        buses = self._scheduler.buses if self._scheduler is not None else []
        if buses:
            for bp in buses:
                for d in bp.devices:
                    cfg = d.config
                    if d.absent:
                        cfg = dataclasses.replace(cfg, fields=tuple(
                            f for f in cfg.fields if f not in d.absent))
                    yield bp.config, cfg
        else:
            yield from self.site.devices()

    def _put(self, out: Out, qos: int | None = None) -> None:
        self.outbox.put(out.topic, out.payload, retain=out.retain,
                        qos=self.settings.qos if qos is None else qos)

    def _log(self, level: int, msg: str, *args: object, device: str | None = None) -> None:
        if self.log_lines:
            extra = {"event": "mqtt", **({"device": device} if device else {})}
            log.log(level, msg, *args, extra=extra)


def from_options(site: Site, url: str | None, *, allow_writes: bool,
                 gateway_id: str | None = None) -> MqttSettings | None:
    """``--mqtt URL`` (and ``--mqtt-id``) over the site file's ``mqtt:`` section (None:
    no MQTT at all)."""
    settings = site.mqtt
    if url:
        from rtupoll.config.mqtt_settings import parse_url

        settings = settings.with_url(url) if settings is not None else parse_url(url)
    if settings is None:
        if allow_writes:
            raise UsageError("--mqtt-allow-writes needs --mqtt URL (or mqtt: in the site file)")
        if gateway_id is not None:
            raise UsageError("--mqtt-id needs --mqtt URL (or mqtt: in the site file)")
        return None
    aiomqtt_module()  # missing: say so now, before any port is opened
    if allow_writes:
        settings = dataclasses.replace(settings, allow_writes=True)
    if gateway_id is not None:
        from rtupoll.config.mqtt_settings import check_gateway_id

        settings = dataclasses.replace(settings, gateway_id=check_gateway_id(gateway_id))
    return settings


def remove_discovery_now(settings: MqttSettings, site: Site) -> Removed:
    """``--mqtt-remove-discovery``, from synchronous code."""
    from rtupoll import aio

    return aio.run(remove_discovery(settings, site))
