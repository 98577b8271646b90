"""``--http`` and its options, defined once for ``poll`` and ``web``."""

from __future__ import annotations

from collections.abc import Callable, MutableMapping, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import click

from rtupoll.config.http_settings import (
    HEADER_TIMEOUT,
    IDLE_TIMEOUT,
    MAX_CONNECTIONS,
    HttpSettings,
    from_options,
    merge,
    require_aiohttp,
)

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.web.service import WebService

F = TypeVar("F", bound=Callable[..., object])
KEYS = ("http", "http_token", "http_users")
LIMIT_KEYS = {"http_header_timeout": "header_timeout", "http_idle_timeout": "idle_timeout",
              "http_max_connections": "max_connections", "http_hosts": "hosts"}


def http_options(*, default: str | None = None) -> Callable[[F], F]:
    def add(f: F) -> F:
        f = click.option("--http-host", "http_hosts", multiple=True, metavar="NAME",
                         help="--http on loopback: also answer requests for this host name "
                              "(a reverse proxy's; repeatable). Other names get 421: the "
                              "guard against DNS rebinding.")(f)
        f = click.option("--http-max-connections", "http_max_connections", type=int,
                         metavar="N", default=None,
                         help=f"--http: connections open at once; more are refused "
                              f"[default: {MAX_CONNECTIONS}].")(f)
        f = click.option("--http-idle-timeout", "http_idle_timeout", type=float,
                         metavar="SECONDS", default=None,
                         help=f"--http: close a connection with no request under way after "
                              f"this long [default: {IDLE_TIMEOUT:g}].")(f)
        f = click.option("--http-header-timeout", "http_header_timeout", type=float,
                         metavar="SECONDS", default=None,
                         help=f"--http: close a connection whose request's headers are not "
                              f"all in this long after its first byte [default: "
                              f"{HEADER_TIMEOUT:g}].")(f)
        f = click.option("--http-user", "http_users", multiple=True, metavar="USER:PASSWORD",
                         envvar="RTUPOLL_HTTP_USER",
                         help="--http: basic authentication for this user (repeatable; "
                              "also $RTUPOLL_HTTP_USER).")(f)
        f = click.option("--http-token", "http_token", metavar="TOKEN", default=None,
                         envvar="RTUPOLL_HTTP_TOKEN",
                         help="--http: require 'Authorization: Bearer TOKEN' (a browser: "
                              "open /?token=TOKEN once); also $RTUPOLL_HTTP_TOKEN.")(f)
        f = click.option("--http", "http", metavar="[HOST:]PORT", default=default,
                         show_default=default is not None,
                         help="Serve the live dashboard, /api/state, /api/events and "
                              "/metrics here (a port alone: loopback only; docs/web.md; "
                              "also http: in the site file).")(f)
        return f
    return add


def pop_http(opts: MutableMapping[str, Any]) -> HttpSettings | None:
    """Take the --http options out of a command's keyword arguments, parsed."""
    listen, token, users = (opts.pop(k, None) for k in KEYS)
    limits = {key: opts.pop(k, None) for k, key in LIMIT_KEYS.items()}
    limits["hosts"] = tuple(limits["hosts"] or ())
    return from_options(listen, token, tuple(users or ()), limits)


def http_service(site: Site, cli: HttpSettings | None, *,
                 served: Callable[[], Sequence[dict[str, Any]]], others: Sequence[object],
                 title: str, say: Callable[[str], None],
                 gateway_id: str | None = None) -> list[WebService]:
    """``--http`` or the site file's ``http:``: the service (none without either).
    ``served``: the gateways' clients the page shows; ``others``: other services'
    collectors for ``/metrics``; ``gateway_id``: the id MQTT publishes under, if any."""
    settings = merge(cli, site.http)
    if settings is None:
        return []
    require_aiohttp()
    if warning := settings.warning():
        say(warning)
    from rtupoll.web.service import WebService

    return [WebService(settings, title=title, served=served, say=say, others=others,
                       cli=cli, gateway=gateway_id)]
