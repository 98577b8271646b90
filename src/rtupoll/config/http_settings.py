"""Where the dashboard listens and who may read it: ``HttpSettings``, pure.

From ``--http HOST:PORT`` (``--http-token``, ``--http-user``) or a site file's
``http:`` (a ``HOST:PORT``, or a mapping with ``listen``, ``token``, ``users``); the
command line wins over the file. A port alone (``8080`` or ``:8080``) listens on the
loopback interface only, as ``--serve`` does: another machine reaches the page only
when a host is named (``0.0.0.0:8080``), and then a token or a user should guard it.

The listener's limits (docs/web.md, "Limits"), each with its default, from the file's
``http:`` mapping or the ``--http-...`` options: ``header_timeout`` (seconds from a
request's first byte to its last header), ``idle_timeout`` (seconds a connection may
stay open with no request under way), ``max_connections`` (open at once; more are
refused), and ``hosts``: the names (beside the loopback ones) a loopback listener
answers to, its guard against DNS rebinding.
"""

from __future__ import annotations

import ipaddress
import math
import re
from collections.abc import Mapping
from dataclasses import field, replace
from typing import TYPE_CHECKING

from rtupoll.config.gateway_settings import LOOPBACK, host_port
from rtupoll.errors import MissingLibrary, UsageError
from rtupoll.frozen import frozen

if TYPE_CHECKING:
    from collections.abc import Callable

    from rtupoll.config.yamlsrc import Node

HTTP_KEYS = {"listen", "token", "users", "header_timeout", "idle_timeout", "max_connections",
             "hosts"}
MIN_SECRET = 8  # characters a token or password has at least
HEADER_TIMEOUT = 10.0  # seconds from a request's first byte to the end of its headers
IDLE_TIMEOUT = 60.0  # seconds a connection may be open with no request under way
MAX_CONNECTIONS = 256  # connections open at once per listener; more are refused
MAX_TIMEOUT = 3600.0  # the largest either timeout may be
MAX_CAP = 100_000
LIMITS = ("header_timeout", "idle_timeout", "max_connections", "hosts")
LOOPBACK_NAMES = ("localhost",)  # and *.localhost (RFC 6761), 127.0.0.0/8, ::1
_NAME = re.compile(r"^(?=.{1,253}$)[a-z0-9_]([a-z0-9_-]{0,61}[a-z0-9_])?"
                   r"(\.[a-z0-9_]([a-z0-9_-]{0,61}[a-z0-9_])?)*\.?$")


@frozen
class HttpSettings:
    host: str
    port: int
    token: str | None = None  # Authorization: Bearer TOKEN (or ?token= once, then a cookie)
    users: Mapping[str, str] = field(default_factory=dict)  # basic auth: user -> password
    header_timeout: float = HEADER_TIMEOUT
    idle_timeout: float = IDLE_TIMEOUT
    max_connections: int = MAX_CONNECTIONS
    hosts: tuple[str, ...] = ()  # other names a loopback listener answers to
    given: frozenset[str] = frozenset()  # the LIMITS the command line set (over the file's)

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

    def allows_host(self, name: str) -> bool:
        """Whether a request's Host (or Origin's host) ``name``, without its port, is this
        listener's: a loopback name or address, or one of ``hosts``. Only a loopback
        listener checks (``loopback``): beyond it, the page is reached by any name."""
        name = name.lower().rstrip(".")
        if name.startswith("[") and name.endswith("]"):
            name = name[1:-1]
        if name in LOOPBACK_NAMES or name.endswith(".localhost") or name in self.hosts:
            return True
        try:
            return ipaddress.ip_address(name).is_loopback
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


def check_limit(key: str, value: object) -> object:
    """A limit's value checked (``UsageError`` without the option's name), as taken."""
    if key == "hosts":
        assert isinstance(value, (list, tuple))
        out = []
        for v in value:
            name = str(v).strip().lower()
            if name.startswith("[") and name.endswith("]"):
                name = name[1:-1]
            try:
                out.append(str(ipaddress.ip_address(name)))
                continue
            except ValueError:
                pass
            if not _NAME.match(name):
                raise UsageError(f"{v!r} is not a host name (a name or an address, no port)")
            out.append(name.rstrip("."))
        return tuple(out)
    if key == "max_connections":
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_CAP:
            raise UsageError(f"{value!r} is outside 1..{MAX_CAP}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UsageError(f"{value!r} is not a number of seconds in (0, {MAX_TIMEOUT:g}]")
    if not math.isfinite(value) or not 0 < value <= MAX_TIMEOUT:
        raise UsageError(f"{value:g} is not a number of seconds in (0, {MAX_TIMEOUT:g}]")
    return float(value)


OPTION = {"header_timeout": "--http-header-timeout", "idle_timeout": "--http-idle-timeout",
          "max_connections": "--http-max-connections", "hosts": "--http-host"}


def from_options(listen: str | None, token: str | None, users: tuple[str, ...],
                 limits: Mapping[str, object] | None = None) -> HttpSettings | None:
    """``--http`` and its options; None without ``--http`` (the site file may still say).
    ``limits``: the ``LIMITS`` the command line gave (None or empty: not given)."""
    if token:
        _check_secret(token, "--http-token")
    parsed = dict(parse_user(u) for u in users)
    given: dict[str, object] = {}
    for key, value in (limits or {}).items():
        if value is None or value == ():
            continue
        try:
            given[key] = check_limit(key, value)
        except UsageError as exc:
            raise UsageError(f"{OPTION[key]} {exc}") from None
    extra: dict[str, object] = {**given, "given": frozenset(given)}
    if listen is None:
        if token or parsed or given:
            # for the site file's listen
            return HttpSettings("", -1, token or None, parsed, **extra)  # type: ignore[arg-type]
        return None
    host, port = parse_listen(listen)
    return HttpSettings(host, port, token or None, parsed, **extra)  # type: ignore[arg-type]


def merge(cli: HttpSettings | None, site: HttpSettings | None) -> HttpSettings | None:
    """The command line's choices over the site file's."""
    if cli is None:
        return site
    if cli.port < 0:  # --http-token, --http-user or a limit without --http
        if site is None:
            raise UsageError("--http-token, --http-user and the --http-... limits need "
                             "--http HOST:PORT (or http: in the site file)")
        cli = replace(cli, host=site.host, port=site.port)
    if site is None:
        return cli
    return replace(site, host=cli.host, port=cli.port, token=cli.token or site.token,
                   users=cli.users or site.users,
                   **{k: getattr(cli, k) for k in cli.given}, given=cli.given)


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
    limits: dict[str, object] = {}
    read: dict[str, Callable[[Node], object]] = {
        "header_timeout": lambda n: n.number(), "idle_timeout": lambda n: n.number(),
        "max_connections": lambda n: n.integer(),
        "hosts": lambda n: [x.text() for x in n.sequence()]}
    for key, how in read.items():
        if key in m:
            try:
                limits[key] = check_limit(key, how(m[key]))
            except UsageError as exc:
                raise m[key].fail(str(exc)) from None
    return HttpSettings(host, port, token, users, **limits)  # type: ignore[arg-type]
