"""The gateway's client counters as Prometheus metrics: a ``prometheus_client``
collector over the running gateways, read at scrape time.

``rtupoll_gateway_requests_total{bus,client,outcome}`` counts requests by what became
of them (``answered``, ``cached`` -- answered from the cache, also in answered --,
``exception``, ``timeout``, ``refused``, ``busy``);
``rtupoll_gateway_queue_wait_seconds{bus,client}`` is a histogram of the time requests
waited for the line; ``rtupoll_gateway_clients{bus}`` the clients connected now.

``client`` is the client's host, never its ``HOST:PORT``: each connection has a new
ephemeral port, so a label with it would be a new series per connection, without
bound. A host's counters are the sum over its connections, kept after they close
(a counter never goes down). The gateway keeps the last ``server.KEEP_CLIENTS``
connections' counters; what a connection counted is taken in at each scrape and when
it is seen closed, so only connections that open and close entirely between two
scrapes, more than ``KEEP_CLIENTS`` of them, can go uncounted.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rtupoll.jobs.histogram import Histogram, appended

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from rtupoll.gateway.clients import ClientStats
    from rtupoll.gateway.server import Gateway

OUTCOMES = ("answered", "cached", "exception", "timeout", "refused", "busy")
# queue waits: nothing when the line is free, a transaction or a poll cycle when not
BUCKETS = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def host_of(peer: str) -> str:
    """``HOST:PORT`` or ``[v6]:PORT`` -> the host (``::1``)."""
    host, sep, port = peer.rpartition(":")
    if not sep or not port.isdigit():
        return peer
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def _counts(c: ClientStats) -> tuple[int, ...]:
    return (c.answered, c.cached, c.exceptions, c.timeouts, c.refused, c.busy)


@dataclass
class HostTotals:
    """One client host's requests and queue waits, over all its connections."""

    closed: list[int] = field(default_factory=lambda: [0] * len(OUTCOMES))  # closed ones'
    waits: Histogram = field(default_factory=lambda: Histogram(BUCKETS))


@dataclass
class _Connection:
    stats: ClientStats
    host: tuple[str, str]  # (bus, client host)
    totals: HostTotals
    last_wait: object = None  # the newest wait already observed (by identity)

    def catch_up(self) -> None:
        """Observe the waits appended to the connection's window since last time."""
        for x in appended(self.stats.waits, self.last_wait):
            self.totals.waits.observe(x)
        if self.stats.waits:
            self.last_wait = self.stats.waits[-1]


class GatewayCollector:
    """The gateways' counters at scrape time; ``gateways`` says which are running now
    (the service's list, which a reload may change)."""

    def __init__(self, gateways: Callable[[], Iterable[Gateway]]) -> None:
        self.gateways = gateways
        self.hosts: dict[tuple[str, str], HostTotals] = {}  # (bus, host) -> totals
        self._open: dict[int, _Connection] = {}  # id(ClientStats) -> connections counting
        self._closed: dict[int, ClientStats] = {}  # taken in, maybe still in the list

    def _take_in(self) -> None:
        """Follow new connections, take in their waits, and fold closed ones' counts into
        their host's (the objects are held, so an ``id`` is never reused meanwhile)."""
        listed: set[int] = set()
        for gw in self.gateways():
            bus = gw.poller.config.name
            for c in gw.clients:
                listed.add(id(c))
                if id(c) not in self._open and id(c) not in self._closed:
                    host = (bus, host_of(c.peer))
                    totals = self.hosts.setdefault(host, HostTotals())
                    self._open[id(c)] = _Connection(c, host, totals)
        for key, conn in list(self._open.items()):  # listed or not: still counting
            conn.catch_up()
            if not conn.stats.connected:  # closed: its counts are final
                for i, n in enumerate(_counts(conn.stats)):
                    conn.totals.closed[i] += n
                del self._open[key]
                self._closed[key] = conn.stats
        for key in [k for k in self._closed if k not in listed]:
            del self._closed[key]  # out of the gateway's list: never seen again

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )

        self._take_in()
        requests = CounterMetricFamily("rtupoll_gateway_requests",
                                       "Gateway client requests by outcome, per client host",
                                       labels=["bus", "client", "outcome"])
        waits = HistogramMetricFamily("rtupoll_gateway_queue_wait_seconds",
                                      "Time gateway requests waited for the line, per "
                                      "client host", labels=["bus", "client"])
        clients = GaugeMetricFamily("rtupoll_gateway_clients",
                                    "Gateway clients connected", labels=["bus"])
        counting = {k: list(t.closed) for k, t in self.hosts.items()}
        for conn in self._open.values():
            row = counting[conn.host]
            for i, n in enumerate(_counts(conn.stats)):
                row[i] += n
        for gw in self.gateways():
            clients.add_metric([gw.poller.config.name], sum(c.connected for c in gw.clients))
        for (bus, host), row in sorted(counting.items()):
            for outcome, n in zip(OUTCOMES, row, strict=True):
                requests.add_metric([bus, host, outcome], n)
            h = self.hosts[bus, host].waits
            waits.add_metric([bus, host], h.buckets(), h.sum)
        yield from (requests, waits, clients)
