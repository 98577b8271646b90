"""Whether what a device answered satisfies one of a profile's identify checks, pure.

Used by ``scan`` (which asks the device) and the sniffer (which overhears another
master ask it): the outcome of reading the check's field is its registers, or the
exception (or other failure) the read met.
"""

from __future__ import annotations

from rtupoll.errors import DeviceException
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Check, Profile


def check_passes(check: Check, profile: Profile, unit: int,
                 outcome: tuple[int, ...] | Exception) -> str | None:
    """Evidence text when ``outcome`` satisfies ``check``, else None."""
    f = profile.field(check.field)
    if isinstance(outcome, DeviceException):
        if check.exception is not None and outcome.code == check.exception:
            return f"{f.name}: exception {outcome.code:02d}, as the profile expects"
        return None
    if not isinstance(outcome, tuple) or len(outcome) != f.words:
        return None
    value = interpret(f, outcome).value
    if isinstance(value, list):
        return None
    if check.equals_address and value != unit:
        return None
    if check.range is not None and (
            isinstance(value, str) or not check.range[0] <= float(value) <= check.range[1]):
        return None
    if check.equals and value not in check.equals:
        return None
    return f"{f.name} = {value}" + (" (its own address)" if check.equals_address else "")
