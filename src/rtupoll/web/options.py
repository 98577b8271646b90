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


def http_service(site: Site, cli: HttpSettings | None, services: Sequence[object], *,
                 title: str, say: Callable[[str], None]) -> list[WebService]:
    """``--http`` or the site file's ``http:``: the service (none without either).
    ``services``: the others, whose gateways' clients the page shows."""
    settings = merge(cli, site.http)
    if settings is None:
        return []
    require_aiohttp()
    if warning := settings.warning():
        say(warning)
    gateways = [s for s in services if callable(getattr(s, "snapshot", None))
                and hasattr(s, "gateways")]

    def served() -> list[dict[str, Any]]:
        return [snap for g in gateways for snap in g.snapshot()]  # type: ignore[attr-defined]

    from rtupoll.web.service import WebService

    return [WebService(settings, title=title, served=served, say=say)]
