"""What a bus's gateway listens on and what it allows: ``ServeConfig``, pure.

Built from ``rtupoll poll --serve HOST:PORT --serve-...`` options or from a site
file bus's ``serve:`` entry (``from_node``), with the same checks.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from dataclasses import field
from typing import TYPE_CHECKING

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen

if TYPE_CHECKING:
    from rtupoll.config.yamlsrc import Node

Network = ipaddress.IPv4Network | ipaddress.IPv6Network
LOOPBACK = "127.0.0.1"
DEFAULT_QUEUE = 16  # client requests waiting for the line beyond each client's first
#                     (all clients together, per bus); more: exception 0x0A
DEFAULT_CLIENT_QUEUE = 4  # one client's requests waiting; beyond: its replies are not
#                            read, so rtupoll stops reading its requests (back-pressure)
DEFAULT_MAX_CLIENTS = 32  # connections per listener; more are closed as they come
DEFAULT_MAX_PER_ADDRESS = 8  # connections from one client address
DEFAULT_TIMEOUT = 0.5  # seconds, for a unit rtupoll does not poll (a polled one: its own)
SCHEMES = {"tcp": "mbap", "modbus": "mbap", "rtu+tcp": "rtu"}
SERVE_KEYS = {"listen", "allow", "read_only", "cache", "broadcast", "setup_writes", "queue",
              "timeout", "client_queue", "max_clients", "max_per_address"}


@frozen
class ServeConfig:
    host: str
    port: int
    framing: str = "mbap"  # "mbap" (Modbus TCP) or "rtu" (RTU frames over TCP)
    allow: tuple[Network, ...] = ()  # client networks; empty: any client that can connect
    read_only: bool = False  # refuse every write (exception 01)
    cache: float = 0.0  # answer reads from polled data at most this old (0: never)
    broadcast: bool = False  # pass unit 0 (broadcast writes) to the line
    setup_writes: frozenset[int] = field(default_factory=frozenset)  # units whose address
    #                                       and baud-rate registers clients may write
    queue: int = DEFAULT_QUEUE
    timeout: float = DEFAULT_TIMEOUT
    client_queue: int = DEFAULT_CLIENT_QUEUE
    max_clients: int = DEFAULT_MAX_CLIENTS
    max_per_address: int = DEFAULT_MAX_PER_ADDRESS

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'rtu+tcp' if self.framing == 'rtu' else 'tcp'}://{host}:{self.port}"


def host_port(text: str, *, default_host: str, port_zero: bool, bare_port: bool = False
              ) -> tuple[str, int] | None:
    """``HOST:PORT``, ``[v6]:PORT`` or ``:PORT`` (``default_host``), and with ``bare_port``
    ``PORT`` alone -> (host, port); None when ``text`` is none of them or the port is out
    of range (0 only with ``port_zero``). Shared with ``--metrics`` (and the site file's
    ``metrics:``), which give their own messages."""
    host, sep, number = text.rpartition(":")
    if not (sep or bare_port) or not number.isdigit() or \
            not (0 if port_zero else 1) <= int(number) <= 65535:
        return None
    return host.strip("[]") or default_host, int(number)


def parse_listen(text: str) -> tuple[str, str, int]:
    """``[SCHEME://][HOST:]PORT`` -> (framing, host, port); the host defaults to loopback.

    SCHEME: ``tcp`` (Modbus TCP, the default) or ``rtu+tcp`` (RTU frames over TCP).
    """
    rest = text.strip()
    framing = "mbap"
    if "://" in rest:
        scheme, rest = rest.split("://", 1)
        if scheme.lower() not in SCHEMES:
            raise UsageError(f"{text!r}: the scheme is tcp:// (Modbus TCP) or rtu+tcp://")
        framing = SCHEMES[scheme.lower()]
    got = host_port(rest.rstrip("/"), default_host=LOOPBACK, port_zero=False, bare_port=True)
    if got is None:
        raise UsageError(f"{text!r}: expected [HOST:]PORT, e.g. 127.0.0.1:5020")
    return framing, *got


def parse_networks(texts: Sequence[str]) -> tuple[Network, ...]:
    out: list[Network] = []
    for t in texts:
        try:
            out.append(ipaddress.ip_network(t.strip(), strict=False))
        except ValueError:
            raise UsageError(f"{t!r} is not a network: expected CIDR like 192.168.1.0/24 "
                             "or an address") from None
    return tuple(out)


def serve_config(listen: str, *, allow: Sequence[str] = (), read_only: bool = False,
                 cache: float = 0.0, broadcast: bool = False, setup_writes: Sequence[int] = (),
                 queue: int = DEFAULT_QUEUE, timeout: float = DEFAULT_TIMEOUT,
                 client_queue: int = DEFAULT_CLIENT_QUEUE,
                 max_clients: int = DEFAULT_MAX_CLIENTS,
                 max_per_address: int = DEFAULT_MAX_PER_ADDRESS) -> ServeConfig:
    """The numbers come checked: by click's ranges (``cli.serve_options``) or ``from_node``."""
    framing, host, port = parse_listen(listen)
    return ServeConfig(host, port, framing, parse_networks(allow), read_only, cache, broadcast,
                       frozenset(setup_writes), queue, timeout, client_queue, max_clients,
                       max_per_address)


def from_node(node: Node) -> ServeConfig:
    """A site file's ``serve:`` -- ``HOST:PORT``, or a mapping (docs/gateway.md)."""
    if not node.is_mapping:
        try:
            return serve_config(node.text())
        except UsageError as exc:
            raise node.fail(str(exc)) from None
    m = node.mapping(SERVE_KEYS, {"listen"})
    try:
        listen = m["listen"].text()
        parse_listen(listen)
    except UsageError as exc:
        raise m["listen"].fail(str(exc)) from None
    allow = [n.text() for n in m["allow"].sequence()] if "allow" in m else []
    try:
        parse_networks(allow)
    except UsageError as exc:
        raise m["allow"].fail(str(exc)) from None
    cache = m["cache"].number() if "cache" in m else 0.0
    if cache < 0:
        raise m["cache"].fail(f"{cache:g} s: expected 0 or more seconds")
    timeout = m["timeout"].number() if "timeout" in m else DEFAULT_TIMEOUT
    if not 0.01 <= timeout <= 30:
        raise m["timeout"].fail(f"{timeout:g} s is outside 0.01..30 s")
    units = [n.integer(1, 247) for n in m["setup_writes"].sequence()] \
        if "setup_writes" in m else []
    return serve_config(
        listen, allow=allow, cache=cache, timeout=timeout, setup_writes=units,
        read_only=m["read_only"].flag() if "read_only" in m else False,
        broadcast=m["broadcast"].flag() if "broadcast" in m else False,
        queue=m["queue"].integer(1, 1000) if "queue" in m else DEFAULT_QUEUE,
        client_queue=m["client_queue"].integer(1, 100) if "client_queue" in m
        else DEFAULT_CLIENT_QUEUE,
        max_clients=m["max_clients"].integer(1, 10000) if "max_clients" in m
        else DEFAULT_MAX_CLIENTS,
        max_per_address=m["max_per_address"].integer(1, 10000) if "max_per_address" in m
        else DEFAULT_MAX_PER_ADDRESS)
