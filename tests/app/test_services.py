"""The composition root (``rtupoll.app.services``): which services ``poll`` runs, in
which order, and what each is handed, built from a real site file."""

from __future__ import annotations

from pathlib import Path

from rtupoll.app.services import poll_services
from rtupoll.config.site import Site, load_site
from rtupoll.jobs.reload import ReloadService
from rtupoll.jobs.services import Service
from rtupoll.outputs.metrics import MetricsService
from rtupoll.ui.systemd import Notifier


class Counting(Service):
    """A service given by the command, with a collector of its own."""

    def collectors(self) -> list[object]:
        return ["the gateway's clients"]


def site(tmp_path: Path, http: str = "") -> Site:
    path = tmp_path / "site.yaml"
    path.write_text("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n"
                    "    devices:\n      - {name: aq, profile: huiwen-aq, address: 3}\n" + http)
    return load_site(path)


def build(s: Site, *, once: bool, metrics: str | None = None) -> list[Service]:
    said: list[str] = []
    return poll_services(s, None, [Counting()], gateway=None, once=once, table=True,
                         metrics=metrics, log_format=None, reload=None, http=None,
                         title="test", say=said.append)


def test_once_runs_the_given_services_and_metrics_only(tmp_path: Path) -> None:
    services = build(site(tmp_path), once=True, metrics="127.0.0.1:0")
    assert [type(s) for s in services] == [Counting, MetricsService]
    metrics = services[1]
    assert isinstance(metrics, MetricsService)
    assert metrics.others == ["the gateway's clients"]  # handed over, not looked for


def test_reload_follows_every_service_before_it_and_systemd_is_told_last(
        tmp_path: Path) -> None:
    # here, not at the top: it imports aiohttp, 0.2 s that every xdist worker would pay
    from rtupoll.web.service import WebService

    services = build(site(tmp_path, "http:\n  listen: 127.0.0.1:0\n"), once=False)
    kinds = [type(s) for s in services]
    assert kinds == [Counting, WebService, ReloadService, Notifier]
    reload = services[2]
    assert isinstance(reload, ReloadService)
    assert list(reload.peers) == services[:2]  # the given service and the dashboard
