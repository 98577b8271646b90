"""Per-client counters of the gateway: for the live table's footer and JSON."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from rtupoll.percentiles import quantile

WAIT_WINDOW = 1000  # queue waits kept for the percentiles


@dataclass
class ClientStats:
    peer: str  # HOST:PORT of the client's connection
    connected: bool = True
    requests: int = 0  # frames received
    answered: int = 0  # normal replies (from the device or the cache)
    cached: int = 0  # of those, from the cache
    exceptions: int = 0  # the device's exception replies, passed through
    timeouts: int = 0  # 0x0B: the device did not answer (or not validly)
    busy: int = 0  # 0x0A: the queue was full or the port gone
    refused: int = 0  # by the access rules or the gateway's own checks
    dropped: int = 0  # not sent: the client had gone before their turn
    waits: deque[float] = field(default_factory=lambda: deque(maxlen=WAIT_WINDOW))
    logged: set[str] = field(default_factory=set)  # refusal reasons already logged

    def wait_p50(self) -> float | None:
        return quantile(self.waits, 50)

    def wait_p95(self) -> float | None:
        return quantile(self.waits, 95)

    def summary(self) -> str:
        """The counters in one line, for the log."""
        p50, p95 = self.wait_p50(), self.wait_p95()
        waits = f", queue wait p50 {p50 * 1000:.0f} ms p95 {p95 * 1000:.0f} ms" \
            if p50 is not None and p95 is not None else ""
        return (f"{self.requests} requests, {self.answered} answered ({self.cached} cached), "
                f"{self.exceptions} exceptions, {self.timeouts} timeouts, {self.refused} "
                f"refused, {self.busy} busy"
                + (f", {self.dropped} dropped unsent" if self.dropped else "") + waits)

    def record(self) -> dict[str, Any]:
        """JSON-ready; waits in seconds, null before the first request waited."""
        return {"client": self.peer, "connected": self.connected, "requests": self.requests,
                "answered": self.answered, "cached": self.cached,
                "exceptions": self.exceptions, "timeouts": self.timeouts, "busy": self.busy,
                "refused": self.refused, "dropped": self.dropped, "wait_p50": self.wait_p50(),
                "wait_p95": self.wait_p95()}
