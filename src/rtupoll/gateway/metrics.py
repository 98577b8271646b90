"""The gateway's per-client counters as Prometheus metrics: a ``prometheus_client``
collector over a running ``GatewayService``, read at scrape time.

``rtupoll_gateway_requests_total{bus,client,outcome}`` counts each client's requests
by what became of them (``answered``, ``cached`` -- answered from the cache, also in
answered --, ``exception``, ``timeout``, ``refused``, ``busy``);
``rtupoll_gateway_queue_wait_seconds{bus,client,quantile}`` is the p50/p95 time its
requests waited for the line; ``rtupoll_gateway_clients{bus}`` the clients connected.
A client is its ``HOST:PORT``; disconnected clients stay until they age out of the
gateway's list (``server.KEEP_CLIENTS``).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from prometheus_client.core import Metric

    from rtupoll.gateway.service import GatewayService


class GatewayCollector:
    def __init__(self, service: GatewayService) -> None:
        self.service = service

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        requests = CounterMetricFamily("rtupoll_gateway_requests",
                                       "Gateway client requests by outcome",
                                       labels=["bus", "client", "outcome"])
        waits = GaugeMetricFamily("rtupoll_gateway_queue_wait_seconds",
                                  "Time a client's requests waited for the line",
                                  labels=["bus", "client", "quantile"])
        clients = GaugeMetricFamily("rtupoll_gateway_clients",
                                    "Gateway clients connected", labels=["bus"])
        for gw in self.service.gateways:
            bus = gw.poller.config.name
            clients.add_metric([bus], sum(c.connected for c in gw.clients))
            for c in gw.clients:
                for outcome, n in (("answered", c.answered), ("cached", c.cached),
                                   ("exception", c.exceptions), ("timeout", c.timeouts),
                                   ("refused", c.refused), ("busy", c.busy)):
                    requests.add_metric([bus, c.peer, outcome], n)
                for q, v in (("0.5", c.wait_p50()), ("0.95", c.wait_p95())):
                    if v is not None:
                        waits.add_metric([bus, c.peer, q], v)
        yield from (requests, waits, clients)
