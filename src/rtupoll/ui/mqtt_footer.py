"""The MQTT service's line under the live table: where it publishes, and how it is going.

Under the table the service writes no log lines: this line says what they would
(connecting, connected, the broker lost and why), with what went out and what waits.
"""

from __future__ import annotations

from rich.text import Text

__all__ = ["line"]


def line(where: str, *, connected: bool, lost_for: float | None, error: str,
         published: int, waiting: int) -> Text:
    """``where``: the broker and base topic; ``lost_for``: seconds since the broker went
    away (None: it has not)."""
    out = Text(f"mqtt {where} · ", style="dim")
    if lost_for is not None:
        out.append(f"broker lost {lost_for:.0f} s ago ({error}), reconnecting",
                   style="yellow")
    elif connected:
        out.append("connected")
    else:
        out.append("connecting")
    out.append(f" · {published} published · {waiting} waiting", style="dim")
    return out
