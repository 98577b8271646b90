"""``rtupoll web --mqtt URL``: the dashboard of every gateway publishing to a broker.

No bus of its own: ``rtupoll.web.fleet`` turns the broker's retained and live messages
into the page ``poll --http`` shows, one section per gateway. The first connection
must succeed (exit 10 otherwise, as ``poll --mqtt``); later the viewer reconnects by
itself and says so on the page.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any
from urllib.parse import unquote, urlsplit

import click

from rtupoll.cli import stop_event
from rtupoll.errors import BrokerError
from rtupoll.web.options import http_options, pop_http

if TYPE_CHECKING:
    from rtupoll.config.mqtt_settings import MqttSettings
    from rtupoll.web.fleet import Fleet

DEFAULT_PREFIX = "rtupoll"
DEFAULT_LISTEN = "127.0.0.1:8080"


@click.command()
@click.option("--mqtt", "url", required=True, metavar="URL",
              help="The broker: mqtt://[USER[:PASS]@]HOST[:PORT][/PREFIX] (mqtts:// for "
                   f"TLS); gateways are found under PREFIX/# [default PREFIX: "
                   f"{DEFAULT_PREFIX}].")
@http_options(default=DEFAULT_LISTEN)
def web(url: str, **opts: Any) -> None:
    """Show every rtupoll gateway that publishes to an MQTT broker, on one web page.

    \b
    rtupoll web --mqtt mqtt://broker.local                 # http://127.0.0.1:8080/
    rtupoll web --mqtt mqtt://broker.local/site-a --http 0.0.0.0:8080 --http-token TOKEN

    Each gateway (rtupoll poll --mqtt) is found by its retained PREFIX/.../bridge/info;
    its devices, values, availability and trends appear grouped by gateway. Read-only.
    Stop with Ctrl-C.
    """
    from rtupoll.config.http_settings import require_aiohttp
    from rtupoll.config.mqtt_settings import parse_url
    from rtupoll.outputs.mqtt_client import aiomqtt_module

    http = pop_http(opts)
    assert http is not None  # --http has a default
    settings = parse_url(url)
    prefix = unquote(urlsplit(url.strip()).path.strip("/")) or DEFAULT_PREFIX
    require_aiohttp()
    aiomqtt_module()
    if warning := http.warning():
        click.echo(f"rtupoll: {warning}", err=True)
    from rtupoll import aio
    from rtupoll.ui import logs

    root = logging.getLogger("rtupoll")
    level = root.level
    # the dropped messages and refused connections, one line a minute, as poll logs them
    handler = logs.setup("text", level=logging.WARNING)
    try:
        aio.run(_main(settings, prefix, http))
    finally:
        root.removeHandler(handler)
        root.setLevel(level)


async def _main(settings: MqttSettings, prefix: str, http: Any) -> None:
    from rtupoll.web.fleet import Fleet
    from rtupoll.web.server import Server

    fleet = Fleet(prefix, f"{settings.where}/{prefix}")
    server = Server(http, fleet)
    stop = stop_event()
    connected = asyncio.Event()
    reader = asyncio.create_task(_read(fleet, settings, prefix, connected))
    waiter = asyncio.create_task(connected.wait())
    await asyncio.wait([reader, waiter], return_when=asyncio.FIRST_COMPLETED)
    if not connected.is_set():
        waiter.cancel()
        reader.result()  # the first connection failed: its BrokerError
    await server.start()
    click.echo(f"rtupoll: fleet of {settings.where}/{prefix}/# on {server.address}", err=True)
    try:
        stopper = asyncio.create_task(stop.wait())
        await asyncio.wait([reader, stopper], return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
    finally:
        reader.cancel()
        await asyncio.gather(reader, return_exceptions=True)
        await server.stop()
        fleet.dropped.flush()


async def _read(fleet: Fleet, settings: MqttSettings, prefix: str,
                connected: asyncio.Event) -> None:
    """Subscribe and feed the fleet; reconnect with backoff once it worked once."""
    from rtupoll.outputs.mqtt import backoff
    from rtupoll.outputs.mqtt_client import describe, make_client

    attempt = 0
    while True:
        try:
            async with make_client(settings, will=False) as client:
                await client.subscribe(f"{prefix}/#", qos=1)
                attempt = 0
                connected.set()
                fleet.set_broker("connected")
                async for message in client.messages:
                    payload = message.payload
                    if not isinstance(payload, bytes):
                        payload = str(payload if payload is not None else "").encode()
                    fleet.handle(str(message.topic), payload)  # never raises
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # aiomqtt.MqttError, OSError: the broker went away
            why = describe(exc, settings)
            if not connected.is_set():
                raise BrokerError(f"--mqtt {settings.where}: {why}") from None
            if fleet.broker == "connected":
                click.echo(f"rtupoll: broker {settings.where}: {why}; reconnecting", err=True)
            fleet.set_broker(f"lost: {why}")
        attempt += 1
        await asyncio.sleep(backoff(attempt))
