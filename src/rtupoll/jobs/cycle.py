"""One device cycle's rules, sans-IO: ``DevicePoller.cycle`` reads the blocks and hands
each block's outcome to a ``CyclePolicy``, which says what comes next. No bus, no clock:
the rules are tested alone (tests/jobs/test_cycle.py).

- A device that failed its last cycle is probed: its first block gets no immediate
  retries (a dead device costs one timeout, not ``1 + retries``); once it answers, the
  rest of the cycle gets the device's retries.
- A timeout before the device has answered in this cycle (it is most likely gone), or
  a second timeout, stops the cycle: the remaining blocks are skipped, not asked.
- An exception reply is an answer (the device is there); a garbled reply is not.
- The next cycle resumes at the first block that failed, so a device that fails
  part-way still gets every block read in turn.
"""

from __future__ import annotations

from rtupoll.jobs.stats import Status


class CyclePolicy:
    """The decisions of one cycle of one device (``spec``: its name in messages)."""

    __slots__ = ("_retries", "answered", "first_failed", "probing", "spec", "stopped",
                 "timeouts")

    def __init__(self, spec: str, *, probing: bool, retries: int) -> None:
        self.spec, self.probing, self._retries = spec, probing, retries
        self.answered = False  # the device answered something in this cycle
        self.timeouts = 0
        self.stopped: str | None = None  # why the rest of the cycle is skipped
        self.first_failed: int | None = None  # the index of the first block that failed

    def retries(self) -> int:
        """Immediate retries for the next block."""
        return 0 if self.probing and not self.answered else self._retries

    def outcome(self, index: int, status: Status) -> None:
        """Block ``index`` of the plan ended with ``status``."""
        if status is Status.OK:
            self.answered = True
            return
        if status is Status.EXCEPTION:
            self.answered = True
        elif status is Status.TIMEOUT:
            self.timeouts += 1
            if not self.answered or self.timeouts > 1:
                self.stopped = f"not read: {self.spec} stopped answering"
        if self.first_failed is None:
            self.first_failed = index

    def resume(self) -> int:
        """Where the next cycle starts."""
        return 0 if self.first_failed is None else self.first_failed

    def succeeded(self, attempted: bool) -> bool:
        """Whether the cycle counts as answered: it did, or it asked nothing (only
        slow blocks, none due; every field absent)."""
        return self.answered or not attempted
