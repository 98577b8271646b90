"""``--http`` and its options, defined once for ``poll`` and ``web``."""

from __future__ import annotations

from collections.abc import Callable, MutableMapping, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import click

from rtupoll.config.http_settings import HttpSettings, from_options, merge, require_aiohttp

if TYPE_CHECKING:
    from rtupoll.config.site import Site
    from rtupoll.web.service import WebService

F = TypeVar("F", bound=Callable[..., object])
KEYS = ("http", "http_token", "http_users")


def http_options(*, default: str | None = None) -> Callable[[F], F]:
    def add(f: F) -> F:
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
    return from_options(listen, token, tuple(users or ()))


def http_service(site: Site, cli: HttpSettings | None, *,
                 served: Callable[[], Sequence[dict[str, Any]]], others: Sequence[object],
                 title: str, say: Callable[[str], None]) -> list[WebService]:
    """``--http`` or the site file's ``http:``: the service (none without either).
    ``served``: the gateways' clients the page shows; ``others``: other services'
    collectors for ``/metrics``."""
    settings = merge(cli, site.http)
    if settings is None:
        return []
    require_aiohttp()
    if warning := settings.warning():
        say(warning)
    from rtupoll.web.service import WebService

    return [WebService(settings, title=title, served=served, say=say, others=others,
                       cli=cli)]
