"""What polling has seen (rtupoll.jobs.stats): who a bus's time is charged to."""

from __future__ import annotations

import pytest

from rtupoll.jobs.stats import BusLoad


class Payer:
    """Someone who pays for bus time (``Charged``), keeping the bill."""

    def __init__(self) -> None:
        self.paid: list[tuple[float, float]] = []

    def charge(self, now: float, seconds: float) -> None:
        self.paid.append((now, seconds))


def test_the_quiet_after_a_failure_is_charged_to_the_device_that_failed() -> None:
    load, slow, other = BusLoad(0.0), Payer(), Payer()
    assert load.add(1.0, 0.1, other)  # its own time: worth a latency sample
    assert load.add(2.0, 0.5, slow, failed=True)  # a timeout: slow pays for it
    assert not load.add(2.6, 0.6, other)  # the drain after it: slow pays again
    assert load.add(3.0, 0.1, other)  # and then everyone pays for their own
    assert slow.paid == [(2.0, 0.5), (2.6, 0.6)]
    assert other.paid == [(1.0, 0.1), (3.0, 0.1)]
    assert load.transactions == 4
    assert load.utilisation(10.0) == pytest.approx(1.3 / 10.0)


def test_after_a_failure_that_is_no_devices_the_next_one_pays_its_own_time() -> None:
    """A gateway client's request (``by`` None) that timed out: the poller's next read
    pays for its own time, though that time is not its own latency."""
    load, dev = BusLoad(0.0), Payer()
    assert load.add(1.0, 0.3, failed=True)
    assert not load.add(1.5, 0.4, dev)
    assert dev.paid == [(1.5, 0.4)]
    assert load.add(2.0, 0.1, dev)
