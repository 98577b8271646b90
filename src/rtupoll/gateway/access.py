"""Who may ask the gateway what: client networks, reserved units, read-only,
broadcasts, state-changing diagnostics, and the registers that would cut a device off
the line (its address and baud rate), pure. Every decision is taken from the
function-effect table (``rtupoll.rtu.effects``).

A refusal is answered with a Modbus exception (the connection stays open), except a
client outside the allowed networks, whose connection is closed at once. Each is
counted per client; the log line is written once per client and reason.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.gateway.pdu import Ask
from rtupoll.model.profile import Field, Profile
from rtupoll.rtu.effects import (
    BROADCAST_FUNCTIONS,
    RESERVED_UNITS,
    TABLE_READS,
    Effect,
    effect,
    writes,
)
from rtupoll.rtu.exception_codes import ExceptionCode
from rtupoll.rtu.functions import FUNCTION_NAMES


@dataclass(frozen=True)
class Refusal:
    code: int  # the exception code the client gets
    reason: str  # short, stable: the log says it once per client


def line_settings(profile: Profile) -> tuple[Field, ...]:
    """The fields that change how the device is reached (``Profile.line_setting``)."""
    return tuple(f for f in profile.fields if profile.line_setting(f))


class Access:
    """The rules of one gateway; ``profiles``: the polled devices' profiles by unit."""

    def __init__(self, config: ServeConfig, profiles: Mapping[int, Profile]) -> None:
        self.config = config
        self.guarded = {unit: line_settings(p) for unit, p in profiles.items()}

    def peer_allowed(self, host: str) -> bool:
        if not self.config.allow:
            return True
        try:
            ip = ipaddress.ip_address(host.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in net for net in self.config.allow)

    def check(self, unit: int, ask: Ask) -> Refusal | None:
        """Why ``ask`` to ``unit`` must not reach the line, or None. Decided from the
        function-effect table (``rtupoll.rtu.effects``): what is not known harmless is
        refused unless a rule allows it."""
        cfg, fc = self.config, ask.function
        if unit in RESERVED_UNITS:
            return Refusal(ExceptionCode.PATH_UNAVAILABLE, f"unit {unit} is reserved in Modbus RTU "
                           "(248-255; 0xFE reaches whoever is there): never forwarded")
        eff = effect(ask.pdu)
        what = _what(ask.pdu)
        if eff is Effect.UNKNOWN:
            return Refusal(ExceptionCode.ILLEGAL_FUNCTION,
                           f"{what}: its effect on a device is unknown")
        if unit == 0:
            if not cfg.broadcast:
                return Refusal(ExceptionCode.PATH_UNAVAILABLE, "broadcast (unit 0) is not allowed")
            if fc not in BROADCAST_FUNCTIONS:
                return Refusal(ExceptionCode.PATH_UNAVAILABLE, "a broadcast can only write "
                               f"(FC 5, 6, 15, 16, 22), not {what}")
        if cfg.read_only and not (eff is Effect.READ and fc in TABLE_READS):
            return Refusal(ExceptionCode.ILLEGAL_FUNCTION, f"{what} is refused (read-only "
                           "gateway: only reads of coils and registers, FC 1-4)")
        setup = unit in cfg.setup_writes
        if eff is Effect.STATE and not setup:
            return Refusal(ExceptionCode.ILLEGAL_FUNCTION, f"{what} changes the device's state (a "
                           "setup_writes unit only)")
        if eff is not Effect.WRITE or setup:
            return None
        runs = writes(ask.pdu)
        if runs is None:
            return Refusal(ExceptionCode.ILLEGAL_FUNCTION, f"{what}: what it writes cannot "
                           "be checked (a setup_writes unit only)")
        fields = self.guarded.get(unit, ()) if unit else \
            tuple(f for fs in self.guarded.values() for f in fs)
        for run in runs:
            for f in fields:
                if run.overlaps(f.table, f.address, f.end):
                    return Refusal(ExceptionCode.ILLEGAL_FUNCTION, f"writing {f.name} of unit "
                                   f"{unit or 'all'} is not allowed (it would change how "
                                   "the device is reached)")
        return None


def _what(pdu: bytes) -> str:
    """A request's function as a log line names it."""
    fc = pdu[0]
    name = FUNCTION_NAMES.get(fc, "")
    if fc == 8 and len(pdu) >= 3:
        return f"FC 8 (diagnostics) sub-function 0x{int.from_bytes(pdu[1:3], 'big'):02X}"
    if fc == 43 and len(pdu) >= 2:
        return f"FC 43 (encapsulated interface) MEI type 0x{pdu[1]:02X}"
    return f"FC {fc} ({name})" if name else f"FC {fc}"
