"""The composition root of ``rtupoll poll``: which services run beside the scheduler,
built from the site and the command's options, and wired to each other here only.

Every service is a ``rtupoll.jobs.services.Service``; what one service needs of another
(the gateway's clients on ``/metrics`` and on the dashboard) is handed over here, so no
layer below reaches up for it.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from rtupoll.jobs.reload import ReloadService, Reopenable

if TYPE_CHECKING:
    from rtupoll.config.http_settings import HttpSettings
    from rtupoll.config.site import Site
    from rtupoll.gateway.service import GatewayService
    from rtupoll.jobs.services import Service


def poll_services(site: Site, writer: Reopenable | None, given: Sequence[Service], *,
                  gateway: GatewayService | None, once: bool, table: bool,
                  metrics: str | None, log_format: str | None,
                  reload: Callable[[], Site] | None, http: HttpSettings | None,
                  title: str, say: Callable[[str], None],
                  gateway_id: str | None = None) -> list[Service]:
    """Every service of ``poll``, in start order: ``given`` (the command's options made
    them: --verify-blocks, the gateway, MQTT), state-change logging (not under the live
    table, which shows the states itself), ``/metrics``, the dashboard, SIGHUP (reload and
    reopen: every service before it follows a reload), and systemd's notify protocol
    last, so READY=1 means everything runs.

    ``/metrics`` and the dashboard serve what the given services count (their
    ``collectors``); the dashboard shows the gateway's clients.

    Logging is on when asked for (``log_format``), when stderr is a terminal or the
    journal, or when the gateway serves (its refusals and dropped clients are an
    operator's business); otherwise (a pipe, a file: a script reading the records)
    only errors."""
    from rtupoll.ui import logs
    from rtupoll.ui.systemd import Notifier

    verbose = log_format is not None or sys.stderr.isatty() or \
        bool(os.environ.get("JOURNAL_STREAM")) or any(b.serve for b in site.buses)
    logs.setup(log_format or "text", level=logging.INFO if verbose else logging.ERROR)
    services = list(given)
    collectors = [c for s in given for c in s.collectors()]
    if verbose and not table and not once:  # --once names each failed device itself
        services.append(logs.StateLog())
    if metrics:
        from rtupoll.outputs.metrics import MetricsService

        services.append(MetricsService(metrics, others=collectors))
    if once:
        return services
    from rtupoll.web.options import http_service

    services += http_service(site, http, served=gateway.snapshot if gateway else list,
                             others=collectors, title=title, say=say, gateway_id=gateway_id)
    notifier = Notifier()

    def notify(what: str) -> None:
        if what == "reloading":
            notifier.reloading()
        else:
            notifier.reloaded("polling")

    services += [ReloadService(reload, writer, notify=notify, peers=list(services),
                               serves=gateway is not None), notifier]
    return services
