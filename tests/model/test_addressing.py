"""Address changes refused before the bus: by the device's range, the profile's reasons, the
'any device' address (rtupoll.model.addressing)."""

from __future__ import annotations

import pytest

from rtupoll.config.library import load_one
from rtupoll.errors import RefusedError
from rtupoll.model.addressing import Change, refuse


@pytest.mark.parametrize(("pid", "new", "why"), [
    ("radar-level", 0, "broadcast"),
    ("radar-level", 248, "outside this device's range 1..247"),
    ("co2meter-an117", 0xFE, "configuration utility"),  # no method wins over the address
    ("net-irnet-pro", 5, "MT-3071 marks register 0x0016 read-only"),
    ("radar-level", 1, "already at 1"),
])
def test_refusals_that_need_no_bus(pid: str, new: int, why: str) -> None:
    with pytest.raises(RefusedError, match=why):
        refuse(Change(load_one(pid), 1, new))


def test_reserved_and_any_addresses_are_refused_with_the_profiles_reason() -> None:
    # a copy of the CO2Meter addresses on a profile that has an address method
    from dataclasses import replace

    co2 = load_one("co2meter-an117")
    radar = replace(load_one("radar-level"), addresses=co2.addresses)
    with pytest.raises(RefusedError, match="reserved: CO2Meter's proprietary protocol"):
        refuse(Change(radar, 1, 0xCC))
    with pytest.raises(RefusedError, match="'any device' address"):
        refuse(Change(radar, 1, 0xFE))
