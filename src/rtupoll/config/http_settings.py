"""Where the dashboard listens and who may read it: ``HttpSettings``, pure.

From ``--http HOST:PORT`` (``--http-token``, ``--http-user``) or a site file's
``http:`` (a ``HOST:PORT``, or a mapping with ``listen``, ``token``, ``users``); the
command line wins over the file. A port alone (``8080`` or ``:8080``) listens on the
loopback interface only, as ``--serve`` does: another machine reaches the page only
when a host is named (``0.0.0.0:8080``), and then a token or a user should guard it.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import field, replace
from typing import TYPE_CHECKING

from rtupoll.config.gateway_settings import LOOPBACK, host_port
from rtupoll.errors import MissingLibrary, UsageError
from rtupoll.frozen import frozen

if TYPE_CHECKING:
    from rtupoll.config.yamlsrc import Node

HTTP_KEYS = {"listen", "token", "users"}
MIN_SECRET = 8  # characters a token or password has at least


@frozen
class HttpSettings:
    host: str
    port: int
    token: str | None = None  # Authorization: Bearer TOKEN (or ?token= once, then a cookie)
    users: Mapping[str, str] = field(default_factory=dict)  # basic auth: user -> password

    @property
    def guarded(self) -> bool:
        return bool(self.token or self.users)

    @property
    def loopback(self) -> bool:
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    def warning(self) -> str:
        """One line when the page is open to the network without a password, else ""."""
        if self.loopback or self.guarded:
            return ""
        return (f"--http {self.host}:{self.port}: the dashboard is readable by anyone who "
                f"can reach this port; guard it with --http-token or --http-user "
                f"(docs/web.md)")


def require_aiohttp() -> None:
    """A one-line error when the ``web`` extra is not installed."""
    try:
        import aiohttp  # noqa: F401
    except ImportError:
        raise MissingLibrary("the dashboard", "web") from None


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[v6]:PORT``, ``:PORT`` or ``PORT`` (these two: loopback)."""
    got = host_port(text.strip(), default_host=LOOPBACK, port_zero=True, bare_port=True)
    if got is None:
        raise UsageError(f"--http {text!r}: expected [HOST:]PORT, e.g. 127.0.0.1:8080")
    return got


def parse_user(text: str) -> tuple[str, str]:
    user, sep, password = text.partition(":")
    if not sep or not user:
        raise UsageError(f"--http-user {user or text!r}: expected USER:PASSWORD")
    _check_secret(password, f"--http-user {user}: the password")
    return user, password


def _check_secret(text: str, what: str) -> None:
    if len(text) < MIN_SECRET:
        raise UsageError(f"{what} is shorter than {MIN_SECRET} characters")


def from_options(listen: str | None, token: str | None, users: tuple[str, ...]
                 ) -> HttpSettings | None:
    """``--http`` and its options; None without ``--http`` (the site file may still say)."""
    if token:
        _check_secret(token, "--http-token")
    parsed = dict(parse_user(u) for u in users)
    if listen is None:
        if token or parsed:
            return HttpSettings("", -1, token or None, parsed)  # for the site file's listen
        return None
    host, port = parse_listen(listen)
    return HttpSettings(host, port, token or None, parsed)


def merge(cli: HttpSettings | None, site: HttpSettings | None) -> HttpSettings | None:
    """The command line's choices over the site file's."""
    if cli is None:
        return site
    if cli.port < 0:  # --http-token or --http-user without --http
        if site is None:
            raise UsageError("--http-token and --http-user need --http HOST:PORT "
                             "(or http: in the site file)")
        cli = replace(cli, host=site.host, port=site.port)
    if site is None:
        return cli
    return replace(cli, token=cli.token or site.token, users=cli.users or site.users)


def from_node(node: Node) -> HttpSettings:
    """A site file's ``http:``: ``HOST:PORT``, or {listen, token, users}."""
    if not node.is_mapping:
        try:
            return HttpSettings(*parse_listen(node.text()))
        except UsageError as exc:
            raise node.fail(str(exc).removeprefix("--http ")) from None
    m = node.mapping(HTTP_KEYS, {"listen"})
    try:
        host, port = parse_listen(m["listen"].text())
    except UsageError as exc:
        raise m["listen"].fail(str(exc).removeprefix("--http ")) from None
    token = m["token"].text() if "token" in m else None
    if token is not None and len(token) < MIN_SECRET:
        raise m["token"].fail(f"shorter than {MIN_SECRET} characters")
    users: dict[str, str] = {}
    if "users" in m:
        for k, v in m["users"].items():
            password = v.text()
            if len(password) < MIN_SECRET:
                raise v.fail(f"the password is shorter than {MIN_SECRET} characters")
            users[k.text()] = password
    return HttpSettings(host, port, token, users)
