"""``rtupoll poll --mqtt URL``: readings to an MQTT broker, commands back, Home Assistant.

A service (``rtupoll.jobs.services``) beside the scheduler, in Zigbee2MQTT's layout:

    BASE/DEVICE                 {"co2": 1175, "co2_level": "GOOD", ..., "last_seen": "..."}
    BASE/DEVICE/availability    online | offline   (retained; offline while backed off)
    BASE/bridge/state           online | offline   (retained; the last will, and a clean stop)
    BASE/DEVICE/FIELD           plain values, when field_topics is on
    BASE/DEVICE/set[/result]    writes (``outputs.mqtt_commands``)
    BASE/DEVICE/get[/result]    reads now, ahead of the schedule

DEVICE is the device's name with every character other than letters, digits, ``_``,
``-`` and ``.`` replaced by ``_`` (``radar-level@4`` -> ``radar-level_4``).

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
import re
import socket
import ssl
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rtupoll.errors import BrokerError, RtupollError, UsageError
from rtupoll.jobs.stats import State, iso_time
from rtupoll.outputs import homeassistant as ha
from rtupoll.outputs import mqtt_commands as cmd
from rtupoll.outputs.mqtt_settings import MqttSettings
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    import aiomqtt
    from rich.text import Text

    from rtupoll.config.site import BusConfig, DeviceConfig, Site
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading

log = logging.getLogger("rtupoll.mqtt")
CONNECT_TIMEOUT = 10.0  # seconds for the first connection before giving up
STOP_FLUSH = 5.0  # seconds a clean stop waits for the last messages to go out
RECONNECT_MIN, RECONNECT_MAX = 0.5, 30.0  # backoff between reconnection attempts
MAX_PENDING = 20_000  # topics the outbox holds at most while the broker is away
MAX_INFLIGHT = 20  # QoS 1/2 messages awaiting their acknowledgement (paho's default)
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")
# paho's own messages ("failed to receive on socket ...") are not for the operator: the
# service says what happened, once, in its own words
_PAHO_LOG = logging.getLogger("rtupoll.mqtt.paho")
_PAHO_LOG.propagate = False
_PAHO_LOG.addHandler(logging.NullHandler())


def topic_name(device: str) -> str:
    """A device's topic level: its name, with anything but ``[A-Za-z0-9_.-]`` as ``_``."""
    return _UNSAFE.sub("_", device)


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


def aiomqtt_module() -> Any:
    """The ``aiomqtt`` library, or one line saying how to install it."""
    try:
        import aiomqtt
    except ImportError:
        raise UsageError("MQTT (--mqtt, or mqtt: in the site file) needs the aiomqtt "
                         "library: pip install 'rtupoll[mqtt]'") from None
    return aiomqtt


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


class MqttService:
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
        self.outbox = Outbox()
        self.published = 0  # messages the broker took
        self._base = settings.base
        self._scheduler: Scheduler | None = None
        self._task: asyncio.Task[None] | None = None
        self._commands: set[asyncio.Task[None]] = set()
        self._connected = asyncio.Event()
        self._flushed = asyncio.Event()
        self._state: dict[str, str] = {}  # topic level -> its latest state payload
        self._avail: dict[str, str] = {}  # topic level -> online/offline
        self._values: dict[str, dict[str, Any]] = {}  # for on_change: values last published
        self._sent_at: dict[str, float] = {}
        self._forced: set[str] = set()  # a get asked for the next state, changed or not
        self._discovered: dict[str, str] = {}  # object id -> config topic, published

    # -- the Service protocol ------------------------------------------------

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = scheduler
        client = self._client()
        try:
            await asyncio.wait_for(client.__aenter__(), CONNECT_TIMEOUT)
        except asyncio.TimeoutError:
            raise BrokerError(f"{self.settings.where}: no answer from the MQTT broker "
                              f"within {CONNECT_TIMEOUT:g} s") from None
        except Exception as exc:  # aiomqtt.MqttError and what it lets through
            raise BrokerError(f"{self.settings.where}: {describe(exc, self.settings)}"
                              ) from None
        self._log(logging.INFO, "mqtt: connected to %s, publishing under %s/",
                  self.settings.where, self._base)
        self._task = asyncio.create_task(self._run(client))
        # subscribed and announced; a session that broke at once goes on reconnecting
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._connected.wait(), CONNECT_TIMEOUT)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        cfg = dev.config
        if self._scheduler is not None and self._scheduler.site is not self.site:
            self._reloaded(self._scheduler.site)
        t = self.topics.get(cfg.name) or topic_name(cfg.name)
        s, base = self.settings, self._base
        avail = "online" if dev.stats.state is State.ONLINE else "offline"
        if self._avail.get(t) != avail:
            self._avail[t] = avail
            self.outbox.put(f"{base}/{t}/availability", avail, retain=True, qos=s.qos)
        values: dict[str, Any] = {}
        error = ""
        for r in readings:
            if r.status == "absent":  # this generation of the device has no such field
                continue
            if r.value is not None:
                values[r.field.name] = cmd.value_of(r.value)
            else:
                values[r.field.name] = None
                if not error or error.startswith("skipped"):
                    error = f"{r.status}: {r.error}"
        opts = s.options(cfg.name)
        now = time.monotonic()
        forced = t in self._forced
        if opts.publish == "on_change" and not forced and self._values.get(t) == values \
                and now - self._sent_at.get(t, -1e18) < opts.max_silence:
            return
        self._forced.discard(t)
        self._values[t], self._sent_at[t] = values, now
        state = dict(values)
        last = dev.stats.last_good_time
        state["last_seen"] = iso_time(last) if last is not None else None
        if error:
            state["error"] = error
        payload = to_json(state)
        self._state[t] = payload
        self.outbox.put(f"{base}/{t}", payload, retain=s.retain, qos=s.qos)
        if opts.field_topics:
            for name, value in values.items():
                if value is not None:
                    self.outbox.put(f"{base}/{t}/{name}", plain(value), retain=s.retain,
                                    qos=s.qos)

    async def stop(self) -> None:
        """Flush what is waiting, say offline (retained), disconnect cleanly."""
        for task in list(self._commands):
            task.cancel()
        await asyncio.gather(*self._commands, return_exceptions=True)
        if self._task is None:
            return
        if self._connected.is_set():
            s = self.settings
            for t in self.topics.values():
                self.outbox.put(f"{self._base}/{t}/availability", "offline", retain=True,
                                qos=max(1, s.qos))
            self.outbox.put(self._bridge, "offline", retain=True, qos=max(1, s.qos))
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

    # -- the connection ------------------------------------------------------

    @property
    def _bridge(self) -> str:
        return f"{self._base}/bridge/state"

    def _client(self) -> aiomqtt.Client:
        return make_client(self.settings, will=True)

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
                except (lib.MqttError, OSError, asyncio.TimeoutError):
                    client = None
                    attempts += 1
                    await asyncio.sleep(backoff(attempts))
                    continue
                gone = time.monotonic() - (lost_at or time.monotonic())
                self.lost_at = None
                self._log(logging.WARNING, "mqtt: back on %s after %.0f s: republishing the "
                          "latest state of %d devices (%d older messages were replaced "
                          "meanwhile)", self.settings.where, gone, len(self._state),
                          self.outbox.dropped)
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
        if s.discovery:
            self._queue_discovery()
        self._queue_latest()
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
                    self._queue_latest()
            elif topic.startswith(configs):
                self._check_config(topic, payload)
            elif topic.startswith(f"{base}/"):
                t, _, verb = topic[len(base) + 1:].rpartition("/")
                name = self._by_topic.get(t)
                if name is not None and verb in ("set", "get"):
                    task = asyncio.create_task(self._command(verb, name, t, payload))
                    self._commands.add(task)
                    task.add_done_callback(self._commands.discard)

    # -- what is published ---------------------------------------------------

    def _queue_latest(self) -> None:
        s = self.settings
        for t, avail in self._avail.items():
            self.outbox.put(f"{self._base}/{t}/availability", avail, retain=True, qos=s.qos)
        for t, payload in self._state.items():
            self.outbox.put(f"{self._base}/{t}", payload, retain=s.retain, qos=s.qos)

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
                self.outbox.put(f"{self._base}/{t}/availability", "", retain=True,
                                qos=self.settings.qos)
                if self.settings.retain:
                    self.outbox.put(f"{self._base}/{t}", "", retain=True,
                                    qos=self.settings.qos)
                self._avail.pop(t, None)
                self._state.pop(t, None)
        self.topics = topics
        self._by_topic = {t: name for name, t in topics.items()}
        if self.settings.discovery:
            self._queue_discovery()

    def _discovery(self) -> dict[str, str]:
        """Every discovery message of the site, by config topic."""
        s = self.settings
        out: dict[str, str] = {}
        buses = self._scheduler.buses if self._scheduler is not None else []
        for bus, dev in self._devices(buses):
            t = self.topics.get(dev.name) or topic_name(dev.name)
            opts = s.options(dev.name)
            controls = {f.name: s.allow_writes and not self.once and (
                not cmd.protected(dev.profile, f) or f.name in opts.allow)
                for f in dev.fields if f.writable}
            oid = ha.object_id(self._base, t)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.device_config(dev, bus, base=self._base, topic=t,
                                                  controls=controls, qos=s.qos))
            self._discovered[oid] = topic
        for bus in {bus.name: bus for bus, _ in self._devices(buses)}.values():
            oid = ha.bus_object_id(self._base, bus.name)
            topic = ha.config_topic(s.discovery_prefix, oid)
            out[topic] = to_json(ha.bus_config(bus, base=self._base, qos=s.qos))
            self._discovered[oid] = topic
        return out

    def _devices(self, buses: list[BusPoller]) -> Iterator[tuple[BusConfig, DeviceConfig]]:
        if buses:
            for bp in buses:
                for d in bp.devices:
                    yield bp.config, d.config
        else:
            yield from self.site.devices()

    def _check_config(self, topic: str, payload: bytes) -> None:
        """A discovery config of ours for a device no longer in the site: remove it."""
        oid = topic.split("/")[-2]
        if not payload or oid in self._discovered:
            return
        try:
            obj = json.loads(payload)
        except ValueError:
            return
        if isinstance(obj, dict) and ha.is_ours(obj, self._base):
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
        """``BASE/DEVICE/set`` or ``.../get``: run it, publish its result on ``.../result``."""
        found = self._find(name)
        if found is None:
            return
        bp, dev = found
        done: dict[str, Any] = {}  # what a set wrote and read back before a failure
        try:
            values = await (self._set(bp, dev, t, payload, done) if verb == "set" else
                            self._get(bp, dev, t, payload))
            if values is None:  # a get of everything: the next state answers it
                return
            result = cmd.ok(values)
        except RtupollError as exc:
            result = cmd.failed(exc, done)
        if verb == "set":
            self._log(logging.INFO, "mqtt: %s: set %s: %s", name,
                      payload.decode("utf-8", "replace")[:200], result.get("error") or "ok",
                      device=name)
        self.outbox.put(f"{self._base}/{t}/{verb}/result", to_json(result), retain=False,
                        qos=self.settings.qos)

    async def _set(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes,
                   done: dict[str, Any]) -> dict[str, Any]:
        cfg = dev.config
        ops = cmd.plan_set(cfg, payload, writes_on=self.settings.allow_writes,
                           allow=self.settings.options(cfg.name).allow)
        await bp.submit(lambda transport: cmd.apply_set(transport, cfg, ops, done))
        self._forced.add(t)
        bp.poll_now(dev)
        return done

    async def _get(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes
                   ) -> dict[str, Any] | None:
        """The fields asked for, read now; None for all of them (the next state)."""
        cfg = dev.config
        fields = cmd.plan_get(cfg, payload)
        if fields is None:
            self._forced.add(t)
            bp.poll_now(dev)
            return None
        return await bp.submit(lambda transport: cmd.apply_get(transport, cfg, fields))


def plain(value: Any) -> str:
    """A value on its own topic: numbers and names as text, flag lists as JSON."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        return to_json(value)
    return str(value)


def backoff(attempt: int, rand: Callable[[], float] = random.random) -> float:
    """Seconds before reconnection attempt ``attempt`` (1, 2, ...): doubling, capped, ±20%."""
    raw = min(RECONNECT_MAX, RECONNECT_MIN * 2.0 ** min(max(0, attempt - 1), 30))
    return float(raw * (0.8 + 0.4 * rand()))


def make_client(settings: MqttSettings, *, will: bool) -> aiomqtt.Client:
    lib = aiomqtt_module()
    s = settings
    tls = None
    if s.tls:
        tls = lib.TLSParameters(ca_certs=s.ca, certfile=s.cert, keyfile=s.key,
                                    cert_reqs=ssl.CERT_REQUIRED)
    last_will = lib.Will(f"{s.base}/bridge/state", "offline", qos=max(1, s.qos),
                             retain=True) if will else None
    client: aiomqtt.Client = lib.Client(
        s.host, s.port, username=s.username, password=s.password,
        identifier=s.client_id or f"rtupoll-{uuid.uuid4().hex[:12]}", will=last_will,
        tls_params=tls, keepalive=30, timeout=CONNECT_TIMEOUT, logger=_PAHO_LOG)
    return client


def describe(exc: BaseException, settings: MqttSettings) -> str:
    """Why a connection failed, in one line an operator can act on."""
    rc = getattr(exc, "rc", None)
    code = getattr(rc, "value", rc)
    text = str(exc)
    refused = type(exc).__name__ == "MqttConnectError"  # the CONNACK said no
    if (refused and code in (4, 5, 134, 135)) or "authori" in text.lower() \
            or "password" in text.lower():
        who = f"user {settings.username!r}" if settings.username else "no user name"
        return f"the broker refused the credentials ({who}): {text}"
    cause = exc.__cause__ or exc.__context__
    for e in (exc, cause):
        if isinstance(e, socket.gaierror) or "Name or service not known" in str(e) or \
                "nodename nor servname" in str(e):
            return f"unknown host {settings.host!r}"
        if isinstance(e, ssl.SSLError) or "SSL" in str(e) or "certificate" in str(e):
            return f"TLS handshake refused: {e}"
        if settings.tls and (isinstance(e, ConnectionResetError) or "reset by peer" in str(e)):
            return (f"TLS handshake refused: the connection was reset (is port "
                    f"{settings.port} a TLS listener?)")
        if isinstance(e, ConnectionRefusedError) or "Connection refused" in str(e):
            return f"connection refused (is the broker running on port {settings.port}?)"
    if "not currently connected" in text or "Disconnected" in text or "connection was lost" \
            in text.lower():
        return "the connection was lost"
    return text or type(exc).__name__


async def remove_discovery(settings: MqttSettings, site: Site) -> list[str]:
    """``--mqtt-remove-discovery``: empty retained payloads for every Home Assistant config
    this gateway (this base topic) published, the site's devices and any it had before;
    returns the object ids removed."""
    lib = aiomqtt_module()
    s = settings
    client = make_client(s, will=False)
    try:
        await asyncio.wait_for(client.__aenter__(), CONNECT_TIMEOUT)
    except asyncio.TimeoutError:
        raise BrokerError(f"{s.where}: no answer from the MQTT broker within "
                          f"{CONNECT_TIMEOUT:g} s") from None
    except Exception as exc:
        raise BrokerError(f"{s.where}: {describe(exc, s)}") from None
    removed: list[str] = []
    try:
        service = MqttService(s, site)
        for topic in service._discovery():
            await client.publish(topic, b"", qos=1, retain=True)
            removed.append(topic.split("/")[-2])
        # every retained config arrives on subscription, before our own marker comes back
        marker = f"{s.base}/bridge/sync/{uuid.uuid4().hex}"
        await client.subscribe(f"{s.discovery_prefix}/device/+/config", qos=1)
        await client.subscribe(marker, qos=1)
        await client.publish(marker, b"1", qos=1)

        async def sweep() -> None:
            async for message in client.messages:
                topic = message.topic.value
                if topic == marker:
                    return
                body = message.payload
                if not isinstance(body, bytes) or not body:
                    continue
                with contextlib.suppress(ValueError):
                    obj = json.loads(body)
                    if isinstance(obj, dict) and ha.is_ours(obj, s.base) and \
                            topic.split("/")[-2] not in removed:
                        await client.publish(topic, b"", qos=1, retain=True)
                        removed.append(topic.split("/")[-2])

        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(sweep(), CONNECT_TIMEOUT)
    except lib.MqttError as exc:
        raise BrokerError(f"{s.where}: {describe(exc, s)}") from None
    finally:
        with contextlib.suppress(Exception):
            await client.__aexit__(None, None, None)
    return removed


def from_options(site: Site, url: str | None, *, allow_writes: bool) -> MqttSettings | None:
    """``--mqtt URL`` over the site file's ``mqtt:`` section (None: no MQTT at all)."""
    settings = site.mqtt
    if url:
        from rtupoll.outputs.mqtt_settings import parse_url

        settings = settings.with_url(url) if settings is not None else parse_url(url)
    if settings is None:
        if allow_writes:
            raise UsageError("--mqtt-allow-writes needs --mqtt URL (or mqtt: in the site file)")
        return None
    aiomqtt_module()  # missing: say so now, before any port is opened
    if allow_writes:
        settings = dataclasses.replace(settings, allow_writes=True)
    return settings


def remove_discovery_now(settings: MqttSettings, site: Site) -> list[str]:
    """``--mqtt-remove-discovery``, from synchronous code."""
    return asyncio.run(remove_discovery(settings, site))
