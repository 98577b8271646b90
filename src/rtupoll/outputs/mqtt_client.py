"""The thin connection: the aiomqtt client rtupoll uses, and why a connection failed.

aiomqtt (2.x, on paho-mqtt 2.x) is an optional extra, imported only here and only
when MQTT is used.

**The socket race** (``SafeClient``). paho calls ``on_socket_open`` and
``on_socket_register_write`` with its socket; aiomqtt 2.x answers by scheduling
``loop.add_reader(sock.fileno(), ...)`` / ``loop.add_writer(sock.fileno(), ...)`` with
``call_soon_threadsafe``, the descriptor's *number* taken at once. When the broker goes
away (or a dead client is collected), paho closes that socket before the loop runs the
scheduled call, which then registers a closed descriptor: the loop logs "Exception in
callback BaseSelectorEventLoop.add_writer() ... OSError: [Errno 9] Bad file
descriptor" with a traceback; had the number been taken meanwhile by a new socket (the
reconnection's, a dashboard client's, a reopened port's), the dead client's callback
would be registered on it, in place of its owner's. ``SafeClient`` schedules the same
registration but decides when it runs: only if that socket is still the client's and
still open (and, for the writer, paho still has something to write). The read and write
callbacks are aiomqtt's, so what happens on a live socket does not change.

aiomqtt 2.x has no public way to this: its constructor binds paho's four socket hooks
to its own methods and takes no loop or hook of the caller's; its 3.0 line (paho gone)
manages the socket itself. ``on_socket_unregister_write`` and ``on_socket_close`` act at
once, on a socket paho has not closed yet, and stay aiomqtt's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import uuid
from functools import cache
from typing import TYPE_CHECKING, Any

from rtupoll.errors import MissingLibrary

if TYPE_CHECKING:
    import aiomqtt

    from rtupoll.config.mqtt_settings import MqttSettings

CONNECT_TIMEOUT = 10.0  # seconds for a connection before giving up
KEEPALIVE = 30
# paho's own messages ("failed to receive on socket ...") are not for the operator: the
# service says what happened, once, in its own words
PAHO_LOG = logging.getLogger("rtupoll.mqtt.paho")
PAHO_LOG.propagate = False
PAHO_LOG.addHandler(logging.NullHandler())


def aiomqtt_module() -> Any:
    """The ``aiomqtt`` library, or one line saying how to install it."""
    try:
        import aiomqtt
    except ImportError:
        raise MissingLibrary("MQTT (--mqtt, or mqtt: in the site file)", "mqtt") from None
    return aiomqtt


def _open(sock: Any) -> bool:
    with contextlib.suppress(OSError, ValueError):
        return bool(sock.fileno() >= 0)
    return False


@cache
def client_class() -> Any:
    """``aiomqtt.Client`` with its two socket registrations made safe (module docstring)."""
    lib = aiomqtt_module()

    class SafeClient(lib.Client):  # type: ignore[misc,name-defined]
        """aiomqtt 2.x binds paho's socket hooks to these methods in its constructor
        and offers no other way in: the two that schedule a registration are replaced,
        each running aiomqtt's own callback only on a socket still the client's and
        open. paho is driven through its public external-loop API (``socket``,
        ``want_write``, ``loop_read``, ``loop_write``); what is aiomqtt's own (the loop,
        the future that says the connection broke, the keepalive task) is used as
        aiomqtt's hooks use it."""

        def _on_socket_open(self, client: Any, userdata: Any, sock: Any) -> None:
            def callback() -> None:  # aiomqtt's reader: read until nothing is pending
                try:
                    while True:
                        client.loop_read()
                        pending = getattr(client.socket(), "pending", None)  # TLS
                        if pending is not None and pending() > 0:
                            continue
                        break
                except Exception as exc:  # the connection broke: aiomqtt's way to say so
                    if not self._disconnected.done():
                        self._disconnected.set_exception(exc)

            def register() -> None:
                if client.socket() is sock and _open(sock):
                    self._loop.add_reader(sock.fileno(), callback)
                    self._misc_task = self._loop.create_task(self._misc_loop())

            self._loop.call_soon_threadsafe(register)

        def _on_socket_register_write(self, client: Any, userdata: Any, sock: Any) -> None:
            def callback() -> None:  # aiomqtt's writer
                try:
                    client.loop_write()
                except Exception as exc:
                    if not self._disconnected.done():
                        self._disconnected.set_exception(exc)

            def register() -> None:
                # paho may have written it all meanwhile (and unregistered): a writer on
                # an idle socket would run on every turn of the loop
                if client.socket() is sock and _open(sock) and client.want_write():
                    self._loop.add_writer(sock.fileno(), callback)

            self._loop.call_soon_threadsafe(register)

    return SafeClient


def make_client(settings: MqttSettings, *, will: bool) -> aiomqtt.Client:
    """A client for ``settings``; ``will``: the last will ``BASE/bridge/state`` = offline."""
    lib = aiomqtt_module()
    s = settings
    tls = None
    if s.tls:
        tls = lib.TLSParameters(ca_certs=s.ca, certfile=s.cert, keyfile=s.key,
                                cert_reqs=ssl.CERT_REQUIRED)
    last_will = lib.Will(f"{s.base}/bridge/state", "offline", qos=max(1, s.qos),
                         retain=True) if will else None
    client: aiomqtt.Client = client_class()(
        s.host, s.port, username=s.username, password=s.password,
        identifier=s.client_id or f"rtupoll-{uuid.uuid4().hex[:12]}", will=last_will,
        tls_params=tls, keepalive=KEEPALIVE, timeout=CONNECT_TIMEOUT, logger=PAHO_LOG)
    return client


async def close(client: aiomqtt.Client) -> None:
    """Leave the client's session, whatever state it is in (never raises)."""
    with contextlib.suppress(Exception):
        await client.__aexit__(None, None, None)


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


async def connect(client: aiomqtt.Client, settings: MqttSettings) -> None:
    """Enter the client's session, or a one-line ``BrokerError``."""
    from rtupoll.errors import BrokerError

    try:
        await asyncio.wait_for(client.__aenter__(), CONNECT_TIMEOUT)
    except TimeoutError:
        raise BrokerError(f"{settings.where}: no answer from the MQTT broker within "
                          f"{CONNECT_TIMEOUT:g} s") from None
    except Exception as exc:  # aiomqtt.MqttError and what it lets through
        raise BrokerError(f"{settings.where}: {describe(exc, settings)}") from None


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
