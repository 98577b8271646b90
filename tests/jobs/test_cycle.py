"""A device cycle's rules (``rtupoll.jobs.cycle.CyclePolicy``), without a bus or a clock:
which retries a block gets, when the rest of a cycle is skipped, where the next cycle
resumes, and whether the cycle counts as answered. ``tests/jobs/test_scheduler.py`` shows
the same rules through ``DevicePoller.cycle`` in virtual time."""

from __future__ import annotations

from rtupoll.jobs.cycle import CyclePolicy
from rtupoll.jobs.stats import Status

OK, TIMEOUT, EXC, GARBLED = Status.OK, Status.TIMEOUT, Status.EXCEPTION, Status.GARBLED


def run(policy: CyclePolicy, outcomes: list[Status]) -> list[tuple[int, str | None]]:
    """Each block's retries and whether it was skipped, as the driver would see them."""
    seen: list[tuple[int, str | None]] = []
    for i, status in enumerate(outcomes):
        seen.append((policy.retries(), policy.stopped))
        if policy.stopped is None:
            policy.outcome(i, status)
    return seen


def test_a_healthy_cycle_reads_every_block_with_the_devices_retries() -> None:
    p = CyclePolicy("air@3", probing=False, retries=2)
    assert run(p, [OK, OK, OK]) == [(2, None)] * 3
    assert p.succeeded(attempted=True) and p.resume() == 0


def test_a_probe_gets_no_retries_until_the_device_answers() -> None:
    p = CyclePolicy("air@3", probing=True, retries=2)
    assert [r for r, _ in run(p, [OK, OK, OK])] == [0, 2, 2]
    gone = CyclePolicy("air@3", probing=True, retries=2)
    assert run(gone, [TIMEOUT, OK, OK]) == [
        (0, None), (0, "not read: air@3 stopped answering"),
        (0, "not read: air@3 stopped answering")]
    assert not gone.succeeded(attempted=True) and gone.resume() == 0


def test_a_first_timeout_after_an_answer_goes_on_and_a_second_stops_the_cycle() -> None:
    p = CyclePolicy("air@3", probing=False, retries=1)
    seen = run(p, [OK, TIMEOUT, OK, TIMEOUT, OK])
    assert [s for _, s in seen] == [None, None, None, None,
                                    "not read: air@3 stopped answering"]
    assert p.succeeded(attempted=True)
    assert p.resume() == 1  # the next cycle starts at the first block that failed


def test_an_exception_is_an_answer_and_a_garbled_reply_is_not() -> None:
    exc = CyclePolicy("air@3", probing=True, retries=1)
    run(exc, [EXC])
    assert exc.succeeded(attempted=True) and exc.retries() == 1 and exc.resume() == 0
    garbled = CyclePolicy("air@3", probing=True, retries=1)
    run(garbled, [OK, GARBLED, GARBLED])
    assert garbled.stopped is None and garbled.resume() == 1
    only = CyclePolicy("air@3", probing=False, retries=1)
    run(only, [GARBLED])
    assert not only.succeeded(attempted=True)


def test_a_cycle_that_asked_nothing_has_not_failed() -> None:
    assert CyclePolicy("air@3", probing=True, retries=1).succeeded(attempted=False)
