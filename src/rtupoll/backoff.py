"""One backoff rule for everything that waits longer after each failure in a row.

``after_failures(n, first=F, cap=C)``: after ``n`` failures (1, 2, ...) wait
``F * factor ** (n-1)``, at most ``C``, scaled by a random factor within ``1 ± jitter``
so that things that failed together do not come back in lockstep. Pure: the caller
counts the failures, gives the randomness and keeps the time.

Who uses it, with the figures its documentation gives (first, cap, jitter):

- a device with no valid reply (``jobs.scheduler.Backoff``): max(1 s, interval), 60 s,
  ±20 % (docs/polling.md);
- a port that went away, its bus paused (``jobs.scheduler``): 1 s, 10 s, none
  (docs/polling.md);
- a unit the gateway does not poll, after 3 timeouts (``gateway.server.SilentUnits``):
  1 s, 30 s, none (docs/gateway.md);
- reconnecting to the MQTT broker (``outputs.mqtt``): 0.5 s, 30 s, ±20 % (docs/mqtt.md).
"""

from __future__ import annotations

import random
from collections.abc import Callable

MAX_STEPS = 64  # the cap is reached long before; a larger power could overflow a float


def after_failures(failures: int, *, first: float, cap: float, factor: float = 2.0,
                   jitter: float = 0.0, rand: Callable[[], float] = random.random) -> float:
    """Seconds to wait after ``failures`` failures in a row (0 or less counts as 1).
    ``rand()`` is in [0, 1); 0.5 is the middle, with no jitter at all."""
    raw = min(cap, first * factor ** min(max(0, failures - 1), MAX_STEPS))
    return raw * (1 + jitter * (2 * rand() - 1)) if jitter else raw
