"""The gateway's part of the live table's footer: one line per client, recent events."""

from __future__ import annotations

from collections.abc import Sequence

from rich.console import Group, RenderableType
from rich.text import Text

from rtupoll.gateway.server import Gateway
from rtupoll.ui.grid import Column, Grid

SHOWN = 6  # client rows per gateway (connected ones first)


def render(gateways: Sequence[Gateway]) -> RenderableType:
    parts: list[RenderableType] = []
    for gw in gateways:
        connected = sum(c.connected for c in gw.clients)
        head = Text("gateway ", style="bold")
        head.append(gw.config.url, style="bold")
        head.append(f" · bus {gw.poller.config.name} · {connected} connected"
                    f" · {gw.pending} queued")
        if gw.cache is not None:
            head.append(f" · cache {gw.config.cache:g} s, {gw.cache.hits} hits")
        parts.append(head)
        clients = sorted(gw.clients, key=lambda c: not c.connected)[:SHOWN]
        if clients:
            t = Grid([Column(col, "left" if col == "  client" else "right")
                      for col in ("  client", "requests", "answered", "except", "timeout",
                                  "refused", "busy", "wait p50", "p95")],
                     header_style="dim", lines=False)  # (as the health table above it)
            for c in clients:
                t.add_row(Text("  " + c.peer, style="" if c.connected else "dim"),
                          str(c.requests), str(c.answered), _n(c.exceptions), _n(c.timeouts),
                          _n(c.refused), _n(c.busy), _ms(c.wait_p50()), _ms(c.wait_p95()))
            parts.append(t)
        for line in gw.events:
            parts.append(Text("  " + line, style="yellow"))
    return Group(*parts)


def _n(n: int) -> Text:
    return Text(str(n), style="red" if n else "dim")


def _ms(seconds: float | None) -> str:
    return "—" if seconds is None else f"{seconds * 1000:.0f} ms"
