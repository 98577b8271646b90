"""The broker connection of ``poll --mqtt``: sessions, reconnecting with backoff, and
what the operator is told about the broker.

The first connection's failure ends ``poll`` (a ``BrokerError``, one line), and so does
another live gateway under the same base topic. After that the broker may go away at
any time: polling goes on, the connection is retried with backoff, and the operator
gets one log line when the broker goes and one when it is back.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import random
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING

from rtupoll.backoff import after_failures
from rtupoll.errors import BrokerError
from rtupoll.numbers import count
from rtupoll.outputs.mqtt_client import (
    CONNECT_TIMEOUT,
    aiomqtt_module,
    close,
    connect,
    describe,
    make_client,
    retained,
)

if TYPE_CHECKING:
    import aiomqtt

    from rtupoll.config.mqtt_settings import MqttSettings
    from rtupoll.outputs.mqtt_outbox import Outbox

__all__ = ["RECONNECT_MAX", "RECONNECT_MIN", "Connection", "Say", "backoff", "check_alone"]

RECONNECT_MIN, RECONNECT_MAX = 0.5, 30.0  # backoff between reconnection attempts
Say = Callable[..., None]  # (level, message, *args): a log line, or nothing


def backoff(attempt: int, rand: Callable[[], float] = random.random) -> float:
    """Seconds before reconnection attempt ``attempt`` (1, 2, ...): doubling, capped, ±20%
    (``rtupoll.backoff``)."""
    return after_failures(attempt, first=RECONNECT_MIN, cap=RECONNECT_MAX, jitter=0.2,
                          rand=rand)


async def check_alone(client: aiomqtt.Client, settings: MqttSettings) -> None:
    """Refuse to start when another live gateway holds this base topic: its
    ``bridge/state`` retained ``online`` and its ``bridge/info`` naming another id.
    (The same id online is this gateway's own previous run, whose last will the
    broker has not published yet.)"""
    base, me = settings.base, settings.gateway_id
    got = await retained(client, base, [f"{base}/bridge/state", f"{base}/bridge/info"])
    if got.get(f"{base}/bridge/state", b"").strip() != b"online":
        return
    other = ""
    with contextlib.suppress(ValueError, AttributeError):
        other = str(json.loads(got.get(f"{base}/bridge/info", b"{}")).get("gateway", ""))
    if other and other != me:
        raise BrokerError(
            f"{settings.where}: gateway {other!r} is online under the base topic "
            f"{base!r}; give this one ({me!r}) its own (--mqtt-id, or a base in the URL), "
            f"or if {other!r} is gone for good: mosquitto_pub -r -n -t {base}/bridge/state")


class Connection:
    """One broker for as long as the service runs: whether a session is up, and since
    when and why it is not."""

    def __init__(self, settings: MqttSettings, outbox: Outbox, say: Say) -> None:
        self.settings = settings
        self.outbox = outbox  # its drops since the broker went are in the "back on" line
        self.say = say
        self.lost_at: float | None = None  # when the broker went away (None: connected)
        self.last_error = ""
        self.connected = asyncio.Event()  # a session is up (subscribed and announced)

    def client(self) -> aiomqtt.Client:
        return make_client(self.settings, will=True)

    async def open(self) -> aiomqtt.Client:
        """The first session's client, or a ``BrokerError`` (no broker, refused, another
        gateway online under this base topic)."""
        client = self.client()
        await connect(client, self.settings)
        try:
            await check_alone(client, self.settings)
        except BaseException:
            await close(client)
            raise
        return client

    async def run(self, client: aiomqtt.Client | None,
                  session: Callable[[aiomqtt.Client], Awaitable[None]],
                  kept: Callable[[], int]) -> None:
        """``session`` on each connection until cancelled; after a lost one, reconnect
        with backoff. ``kept``: the devices whose latest state is published again."""
        lib = aiomqtt_module()
        lost_at: float | None = None
        attempts = 0
        while True:
            if client is None:
                client = self.client()
                try:
                    await asyncio.wait_for(client.__aenter__(), CONNECT_TIMEOUT)
                except (TimeoutError, lib.MqttError, OSError):
                    client = None
                    attempts += 1
                    await asyncio.sleep(backoff(attempts))
                    continue
                gone = time.monotonic() - (lost_at or time.monotonic())
                self.lost_at = None
                self.say(logging.WARNING, "mqtt: back on %s after %.0f s: republishing the "
                         "latest state of %s (%s replaced meanwhile)", self.settings.where,
                         gone, count(kept(), "device"),
                         count(self.outbox.dropped, "older message"))
            attempts = 0
            reason = "disconnected"
            try:
                await session(client)
            except lib.MqttError as exc:
                reason = describe(exc, self.settings)
            finally:
                self.connected.clear()
                await close(client)
            client = None
            lost_at = self.lost_at = time.monotonic()
            self.last_error = reason
            self.outbox.dropped = 0
            self.say(logging.ERROR, "mqtt: lost the broker %s (%s): polling goes on, "
                     "keeping each device's latest state; reconnecting",
                     self.settings.where, reason)
