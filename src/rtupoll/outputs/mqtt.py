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

The rooms: ``mqtt_state`` turns readings into messages (pure), ``homeassistant`` the
site into discovery (pure), ``mqtt_commands`` checks and runs commands,
``mqtt_client`` is the connection; this module is the service that joins them.

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
import json
import logging
import random
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rtupoll.backoff import after_failures
from rtupoll.config.mqtt_settings import MqttSettings
from rtupoll.errors import BrokerError, RtupollError, UsageError
from rtupoll.figures import count
from rtupoll.jobs.services import Follow, Service
from rtupoll.jobs.stats import State
from rtupoll.outputs import homeassistant as ha
from rtupoll.outputs import mqtt_commands as cmd
from rtupoll.outputs.fleet import bridge_info, version
from rtupoll.outputs.mqtt_client import (
    CONNECT_TIMEOUT,
    aiomqtt_module,
    connect,
    describe,
    make_client,
)
from rtupoll.outputs.mqtt_state import Out, StatePublisher, plain, topic_name
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    import aiomqtt
    from rich.text import Text

    from rtupoll.config.site import BusConfig, DeviceConfig, Site
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.services import Reload
    from rtupoll.jobs.stats import Reading

__all__ = ["MqttService", "Outbox", "Removed", "backoff", "describe", "device_topics",
           "from_options", "plain", "remove_discovery_now", "topic_name"]

log = logging.getLogger("rtupoll.mqtt")
STOP_FLUSH = 5.0  # seconds a clean stop waits for the last messages to go out
RECONNECT_MIN, RECONNECT_MAX = 0.5, 30.0  # backoff between reconnection attempts
MAX_PENDING = 20_000  # topics the outbox holds at most while the broker is away
MAX_INFLIGHT = 20  # QoS 1/2 messages awaiting their acknowledgement (paho's default)


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


@dataclass(frozen=True)
class Message:
    payload: str
    retain: bool
    qos: int


class Outbox:
    """Messages waiting for the broker: the latest per topic, oldest topic first."""

    def __init__(self, limit: int = MAX_PENDING) -> None:
        self._pending: dict[str, Message] = {}
        self.limit = limit
        self.dropped = 0  # messages replaced by a newer one on the same topic, or over limit
        self.ready = asyncio.Event()

    def put(self, topic: str, payload: str, *, retain: bool, qos: int) -> None:
        if topic in self._pending:
            self.dropped += 1
        elif len(self._pending) >= self.limit:
            self.dropped += 1
            return
        self._pending[topic] = Message(payload, retain, qos)
        self.ready.set()

    def pop(self) -> tuple[str, Message] | None:
        if not self._pending:
            self.ready.clear()
            return None
        topic = next(iter(self._pending))
        return topic, self._pending.pop(topic)

    def restore(self, topic: str, msg: Message) -> None:
        """Put back a message that could not be sent (unless a newer one came meanwhile)."""
        if topic not in self._pending:
            self._pending[topic] = msg
            self.ready.set()

    def __len__(self) -> int:
        return len(self._pending)


class MqttService(Service):
    """The MQTT side of ``poll``: see the module docstring."""

    def __init__(self, settings: MqttSettings, site: Site, *, once: bool = False,
                 log_lines: bool = True) -> None:
        """``log_lines=False``: no log lines (under the live table ``footer`` says it)."""
        self.settings = settings
        self.log_lines = log_lines
        self.lost_at: float | None = None  # when the broker went away (None: connected)
        self.last_error = ""
        self.site = site
        self.once = once  # poll --once: publish one scan; take no commands
        self.topics = device_topics(site)
        self._by_topic = {t: name for name, t in self.topics.items()}  # commands' device
        self.publisher = StatePublisher(settings, self.topics)
        self.outbox = Outbox()
        self.published = 0  # messages the broker took
        self._base = settings.base
        self._scheduler: Scheduler | None = None
        self._task: asyncio.Task[None] | None = None
        self._commands: set[asyncio.Task[None]] = set()
        self._connected = asyncio.Event()
        self._flushed = asyncio.Event()
        self._discovered: dict[str, str] = {}  # object id -> config topic, published
        self._retained_said = False  # a retained command was ignored, and the log said so
        # device -> the fields its generation lacks, as announced (a variant learned)
        self._absent: dict[str, frozenset[str]] = {}

    # -- the Service protocol ------------------------------------------------

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = scheduler
        client = self._client()
        await connect(client, self.settings)
        try:
            await self._check_alone(client)
        except BaseException:
            with contextlib.suppress(Exception):
                await client.__aexit__(None, None, None)
            raise
        self._log(logging.INFO, "mqtt: connected to %s as gateway %s, publishing under %s/",
                  self.settings.where, self.settings.gateway_id, self._base)
        self._task = asyncio.create_task(self._run(client))
        # subscribed and announced; a session that broke at once goes on reconnecting
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._connected.wait(), CONNECT_TIMEOUT)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        for out in self.publisher.readings(dev.config, dev.stats.state is State.ONLINE,
                                           dev.stats.last_good_time, readings):
            self._put(out)
        absent = frozenset(f.name for f in dev.absent)
        if absent != self._absent.get(dev.config.name, frozenset()):
            # the device said which generation it is: announce it without the fields it
            # lacks (Home Assistant drops those entities, never unknown for ever)
            self._absent[dev.config.name] = absent
            if self._connected.is_set():
                self._queue_info()
            if self.settings.discovery:
                self._queue_discovery()

    async def on_reload(self, site: Site) -> Reload:
        """Topics and discovery follow the new site once the scheduler has it."""
        def then(scheduler: Scheduler) -> list[str]:
            self._reloaded(scheduler.site)
            return []
        return Follow(then)

    async def stop(self) -> None:
        """Flush what is waiting, say offline (retained), disconnect cleanly."""
        for task in list(self._commands):
            task.cancel()
        await asyncio.gather(*self._commands, return_exceptions=True)
        if self._task is None:
            return
        if self._connected.is_set():
            qos = max(1, self.settings.qos)
            for out in self.publisher.offline():
                self._put(out, qos)
            self.outbox.put(self._bridge, "offline", retain=True, qos=qos)
            self._flushed.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._flushed.wait(), STOP_FLUSH)
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)

    def footer(self) -> Text:
        """The live table's line: where it publishes, and how it is going."""
        from rich.text import Text

        line = Text(f"mqtt {self.settings.where}/{self._base} · ", style="dim")
        if self.lost_at is not None:
            line.append(f"broker lost {time.monotonic() - self.lost_at:.0f} s ago "
                        f"({self.last_error}), reconnecting", style="yellow")
        elif self._connected.is_set():
            line.append("connected")
        else:
            line.append("connecting")
        line.append(f" · {self.published} published · {len(self.outbox)} waiting",
                    style="dim")
        return line

    def _log(self, level: int, msg: str, *args: object, device: str | None = None) -> None:
        if self.log_lines:
            extra = {"event": "mqtt", **({"device": device} if device else {})}
            log.log(level, msg, *args, extra=extra)

    def _put(self, out: Out, qos: int | None = None) -> None:
        self.outbox.put(out.topic, out.payload, retain=out.retain,
                        qos=self.settings.qos if qos is None else qos)

    # -- the connection ------------------------------------------------------

    @property
    def _bridge(self) -> str:
        return f"{self._base}/bridge/state"

    def _client(self) -> aiomqtt.Client:
        return make_client(self.settings, will=True)

    async def _check_alone(self, client: aiomqtt.Client) -> None:
        """Refuse to start when another live gateway holds this base topic: its
        ``bridge/state`` retained ``online`` and its ``bridge/info`` naming another id.
        (The same id online is this gateway's own previous run, whose last will the
        broker has not published yet.)"""
        base, me = self._base, self.settings.gateway_id
        got = await retained(client, base, [f"{base}/bridge/state", f"{base}/bridge/info"])
        if got.get(f"{base}/bridge/state", b"").strip() != b"online":
            return
        other = ""
        with contextlib.suppress(ValueError, AttributeError):
            other = str(json.loads(got.get(f"{base}/bridge/info", b"{}")).get("gateway", ""))
        if other and other != me:
            raise BrokerError(
                f"{self.settings.where}: gateway {other!r} is online under the base topic "
                f"{base!r}; give this one ({me!r}) its own (--mqtt-id, or a base in the URL), "
                f"or if {other!r} is gone for good: mosquitto_pub -r -n -t {base}/bridge/state")

    async def _run(self, client: aiomqtt.Client | None) -> None:
        """Sessions until cancelled; after a lost connection, reconnect with backoff."""
        lib = aiomqtt_module()
        lost_at: float | None = None
        attempts = 0
        while True:
            if client is None:
                client = self._client()
                try:
                    await asyncio.wait_for(client.__aenter__(), CONNECT_TIMEOUT)
                except (TimeoutError, lib.MqttError, OSError):
                    client = None
                    attempts += 1
                    await asyncio.sleep(backoff(attempts))
                    continue
                gone = time.monotonic() - (lost_at or time.monotonic())
                self.lost_at = None
                self._log(logging.WARNING, "mqtt: back on %s after %.0f s: republishing the "
                          "latest state of %s (%s replaced meanwhile)", self.settings.where, gone,
                          count(len(self.publisher.state), "device"),
                          count(self.outbox.dropped, "older message"))
            attempts = 0
            reason = "disconnected"
            try:
                await self._session(client)
            except lib.MqttError as exc:
                reason = describe(exc, self.settings)
            finally:
                self._connected.clear()
                with contextlib.suppress(Exception):
                    await client.__aexit__(None, None, None)
            client = None
            lost_at = self.lost_at = time.monotonic()
            self.last_error = reason
            self.outbox.dropped = 0
            self._log(logging.ERROR, "mqtt: lost the broker %s (%s): polling goes on, "
                      "keeping each device's latest state; reconnecting",
                      self.settings.where, reason)

    async def _session(self, client: aiomqtt.Client) -> None:
        s, base = self.settings, self._base
        subs = [(f"{s.discovery_prefix}/status", s.qos)]
        if not self.once:
            subs += [(f"{base}/+/set", s.qos), (f"{base}/+/get", s.qos)]
        if s.discovery:
            subs.append((f"{s.discovery_prefix}/device/+/config", s.qos))
        await client.subscribe(subs)
        await client.publish(self._bridge, "online", qos=max(1, s.qos), retain=True)
        self._queue_info()
        if s.discovery:
            self._queue_discovery()
        for out in self.publisher.latest():
            self._put(out)
        self._connected.set()
        reader = asyncio.create_task(self._read(client))
        writer = asyncio.create_task(self._write(client))
        try:
            done, _ = await asyncio.wait([reader, writer], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                task.result()
        finally:
            for task in (reader, writer):
                task.cancel()
            await asyncio.gather(reader, writer, return_exceptions=True)

    async def _write(self, client: aiomqtt.Client) -> None:
        """Publish from the outbox. QoS 0 goes out one message after the other; QoS 1
        and 2 keep up to ``MAX_INFLIGHT`` messages awaiting their acknowledgement, so a
        distant broker's round trip does not set the pace."""
        inflight: set[asyncio.Task[None]] = set()
        errors: list[BaseException] = []
        window = asyncio.Semaphore(MAX_INFLIGHT)

        def finished(task: asyncio.Task[None]) -> None:
            inflight.discard(task)
            if not task.cancelled() and task.exception() is not None:
                errors.append(task.exception())  # type: ignore[arg-type]

        try:
            while True:
                if errors:
                    raise errors[0]
                item = self.outbox.pop()
                if item is None:
                    if inflight:
                        await asyncio.wait(set(inflight))
                        continue
                    self._flushed.set()
                    await self.outbox.ready.wait()
                    continue
                topic, msg = item
                if msg.qos == 0:
                    await self._send(client, topic, msg)
                    continue
                await window.acquire()
                task = asyncio.create_task(self._send(client, topic, msg, window))
                inflight.add(task)
                task.add_done_callback(finished)
        finally:
            for task in list(inflight):
                task.cancel()
            await asyncio.gather(*inflight, return_exceptions=True)

    async def _send(self, client: aiomqtt.Client, topic: str, msg: Message,
                    window: asyncio.Semaphore | None = None) -> None:
        try:
            await client.publish(topic, msg.payload, qos=msg.qos, retain=msg.retain)
        except BaseException:
            self.outbox.restore(topic, msg)  # sent again after reconnecting
            raise
        else:
            self.published += 1
        finally:
            if window is not None:
                window.release()

    async def _read(self, client: aiomqtt.Client) -> None:
        s, base = self.settings, self._base
        status = f"{s.discovery_prefix}/status"
        configs = f"{s.discovery_prefix}/device/"
        async for message in client.messages:
            topic = message.topic.value
            payload = message.payload if isinstance(message.payload, bytes) else \
                str(message.payload if message.payload is not None else "").encode()
            if topic == status:
                if payload.strip() == b"online":  # Home Assistant (re)started
                    if s.discovery:
                        self._queue_discovery()
                    for out in self.publisher.latest():
                        self._put(out)
            elif topic.startswith(configs):
                self._check_config(topic, payload)
            elif topic.startswith(f"{base}/"):
                t, _, verb = topic[len(base) + 1:].rpartition("/")
                name = self._by_topic.get(t)
                if name is None or verb not in ("set", "get"):
                    continue
                if message.retain:  # left on the broker, maybe long ago: not a command now
                    self._ignored_retained(topic)
                    continue
                task = asyncio.create_task(self._command(verb, name, t, payload))
                self._commands.add(task)
                task.add_done_callback(self._commands.discard)

    def _ignored_retained(self, topic: str) -> None:
        if self._retained_said:
            return
        self._retained_said = True
        self._log(logging.WARNING, "mqtt: ignoring the retained command on %s (and any "
                  "other): commands must come from now, not from the broker's memory; clear "
                  "it with: mosquitto_pub -r -n -t '%s'", topic, topic)

    # -- what is published ---------------------------------------------------

    def _queue_info(self) -> None:
        """``BASE/bridge/info``: who this gateway is and what it polls (retained)."""
        info = bridge_info(self.settings.gateway_id, self._base, self._devices(),
                           self.topics, version())
        self.outbox.put(f"{self._base}/bridge/info", to_json(info), retain=True,
                        qos=max(1, self.settings.qos))

    def _queue_discovery(self) -> None:
        """Every config of the site; those of devices no longer in it are removed."""
        before = dict(self._discovered)
        self._discovered.clear()
        for topic, payload in self._discovery().items():
            self.outbox.put(topic, payload, retain=True, qos=self.settings.qos)
        for oid, topic in before.items():
            if oid not in self._discovered:
                self.outbox.put(topic, "", retain=True, qos=self.settings.qos)

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
        self._by_topic = {t: name for name, t in topics.items()}
        if self._connected.is_set():
            self._queue_info()
        if self.settings.discovery:
            self._queue_discovery()

    def _discovery(self) -> dict[str, str]:
        """Every discovery message of the site, by config topic."""
        s = self.settings
        gid = s.gateway_id
        out: dict[str, str] = {}
        for bus, dev in self._devices():
            t = self.topics.get(dev.name) or topic_name(dev.name)
            opts = s.options(dev.name)
            controls = {f.name: s.allow_writes and not self.once and (
                not cmd.protected(dev.profile, f) or f.name in opts.allow)
                for f in dev.fields if f.writable}
            oid = ha.object_id(gid, t)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.device_config(dev, bus, gateway_id=gid, base=self._base,
                                                  topic=t, controls=controls, qos=s.qos))
            self._discovered[oid] = topic
        for bus in {bus.name: bus for bus, _ in self._devices()}.values():
            oid = ha.bus_object_id(gid, bus.name)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.bus_config(bus, gateway_id=gid, base=self._base, qos=s.qos))
            self._discovered[oid] = topic
        return out

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

    def _check_config(self, topic: str, payload: bytes) -> None:
        """A discovery config of ours for a device no longer in the site: remove it."""
        oid = topic.split("/")[-2]
        if not payload or oid in self._discovered:
            return
        try:
            obj = json.loads(payload)
        except (ValueError, RecursionError):
            return
        if isinstance(obj, dict) and ha.is_ours(obj, self.settings.gateway_id, self._base):
            self.outbox.put(topic, "", retain=True, qos=self.settings.qos)
            self._log(logging.INFO, "mqtt: removed the Home Assistant discovery of %s (no "
                      "longer in the site)", oid)

    # -- commands ------------------------------------------------------------

    def _find(self, name: str) -> tuple[BusPoller, DevicePoller] | None:
        if self._scheduler is None:
            return None
        for bp in self._scheduler.buses:
            for d in bp.devices:
                if d.config.name == name:
                    return bp, d
        return None

    async def _command(self, verb: str, name: str, t: str, payload: bytes) -> None:
        """``BASE/DEVICE/set`` or ``.../get``: run it, publish its one result on
        ``.../result``, whatever the payload holds."""
        done: dict[str, Any] = {}  # what a set wrote and read back before a failure
        try:
            found = self._find(name)
            if found is None:
                raise UsageError(f"{name} is not polled now (the site file was reloaded)")
            bp, dev = found
            values = await (self._set(bp, dev, t, payload, done) if verb == "set" else
                            self._get(bp, dev, t, payload))
            if values is None:  # a get of everything: the next state answers it
                return
            result = cmd.ok(values)
        except RtupollError as exc:
            result = cmd.failed(exc, done)
        except Exception as exc:  # a bug: still one result, and one line, no traceback
            result = cmd.failed(RtupollError(f"{verb} failed: {type(exc).__name__}: {exc}"),
                                done)
            self._log(logging.ERROR, "mqtt: %s: %s: %s", name, verb, result["error"],
                      device=name)
        if verb == "set":
            self._log(logging.INFO, "mqtt: %s: set %s: %s", name,
                      payload[:200].decode("utf-8", "replace"), result.get("error") or "ok",
                      device=name)
        self.outbox.put(f"{self._base}/{t}/{verb}/result", to_json(result), retain=False,
                        qos=self.settings.qos)

    async def _set(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes,
                   done: dict[str, Any]) -> dict[str, Any]:
        cfg = dev.config
        ops = cmd.plan_set(cfg, payload, writes_on=self.settings.allow_writes,
                           allow=self.settings.options(cfg.name).allow)
        await bp.submit(lambda transport: cmd.apply_set(transport, cfg, ops, done))
        self.publisher.forced.add(t)
        bp.poll_now(dev)
        return done

    async def _get(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes
                   ) -> dict[str, Any] | None:
        """The fields asked for, read now; None for all of them (the next state)."""
        cfg = dev.config
        fields = cmd.plan_get(cfg, payload)
        if fields is None:
            self.publisher.forced.add(t)
            bp.poll_now(dev)
            return None
        return await bp.submit(lambda transport: cmd.apply_get(transport, cfg, fields))


def backoff(attempt: int, rand: Callable[[], float] = random.random) -> float:
    """Seconds before reconnection attempt ``attempt`` (1, 2, ...): doubling, capped, ±20%
    (``rtupoll.backoff``)."""
    return after_failures(attempt, first=RECONNECT_MIN, cap=RECONNECT_MAX, jitter=0.2,
                          rand=rand)


async def retained(client: aiomqtt.Client, base: str, topics: list[str]) -> dict[str, bytes]:
    """The retained payloads (not empty) of ``topics`` (filters allowed) now: every one
    arrives on subscription, before a marker of our own published after it comes back
    (``CONNECT_TIMEOUT`` at most)."""
    marker = f"{base}/bridge/sync/{uuid.uuid4().hex}"
    got: dict[str, bytes] = {}
    await client.subscribe([(t, 1) for t in [*topics, marker]])
    await client.publish(marker, b"1", qos=1)

    async def collect() -> None:
        async for message in client.messages:
            topic = message.topic.value
            if topic == marker:
                return
            if message.retain and isinstance(message.payload, bytes) and message.payload:
                got[topic] = message.payload

    with contextlib.suppress(asyncio.TimeoutError):
        await asyncio.wait_for(collect(), CONNECT_TIMEOUT)
    await client.unsubscribe([*topics, marker])
    return got


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
        service = MqttService(s, site)
        site_configs = set(service._discovery())
        held = await retained(client, base, [f"{s.discovery_prefix}/device/+/config",
                                             f"{base}/#"])
        configs = [t for t, body in held.items()
                   if t.startswith(f"{s.discovery_prefix}/device/")
                   and (t in site_configs or _ours(body, s))]
        info, state = f"{base}/bridge/info", f"{base}/bridge/state"
        levels = set(service.topics.values()) | _info_levels(held.get(info, b""))
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
        with contextlib.suppress(Exception):
            await client.__aexit__(None, None, None)
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
