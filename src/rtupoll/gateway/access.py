"""Who may ask the gateway what: client networks, read-only, broadcasts, and the
registers that would cut a device off the line (its address and baud rate), pure.

A refusal is answered with a Modbus exception (the connection stays open), except a
client outside the allowed networks, whose connection is closed at once. Each is
counted per client; the log line is written once per client and reason.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass

from rtupoll.gateway.pdu import ILLEGAL_FUNCTION, PATH_UNAVAILABLE, Ask
from rtupoll.gateway.settings import ServeConfig
from rtupoll.model.profile import Field, Profile


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
        """Why ``ask`` to ``unit`` must not reach the line, or None."""
        cfg = self.config
        if unit == 0 and not (cfg.broadcast and ask.write):
            why = "broadcast (unit 0) is not allowed" if not cfg.broadcast else \
                "a broadcast can only write"
            return Refusal(PATH_UNAVAILABLE, why)
        if ask.write and cfg.read_only:
            return Refusal(ILLEGAL_FUNCTION, "writes are refused (read-only gateway)")
        if ask.write and unit not in cfg.setup_writes and ask.table is not None:
            for f in self.guarded.get(unit, ()) if unit else \
                    tuple(f for fs in self.guarded.values() for f in fs):
                if ask.touches(f.table, f.address, f.end):
                    return Refusal(ILLEGAL_FUNCTION, f"writing {f.name} of unit {unit or 'all'} "
                                   "is not allowed (it would change how the device is reached)")
        return None
