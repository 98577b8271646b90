"""``poll --verify-blocks`` and ``poll --remember-holes``: the hole finders as services.

``VerifyBlocks`` runs once the ports are open, before the first cycle: every planned
block that joins several fields is read as a block and field by field
(``jobs.holes.verify_block``); a block that disagrees is reported with its
addresses and the device stops bridging there. ``RememberHoles`` loads the holes a
site's devices taught earlier runs (``jobs.holes.HoleStore``, next to the site file)
and writes down the ones this run learns.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING

from rtupoll.errors import BusError
from rtupoll.jobs.holes import HoleStore, Register, verify_block
from rtupoll.jobs.services import Service

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading

Say = Callable[[str], None]


class VerifyBlocks(Service):
    """Compare each multi-field block with its fields read alone, before polling."""

    def __init__(self, say: Say) -> None:
        self.say = say
        self.checked = 0
        self.mismatches = 0

    async def start(self, scheduler: Scheduler) -> None:
        await asyncio.gather(*(self._bus(bp) for bp in scheduler.buses))
        self.say(f"verify-blocks: {self.checked} blocks checked, "
                 f"{self.mismatches} disagreed with their fields read alone")

    async def _bus(self, bp: BusPoller) -> None:
        for dev in bp.devices:
            await verify_device(dev, bp.transport, self._count, self.say)

    def _count(self, mismatch: bool) -> None:
        self.checked += 1
        self.mismatches += mismatch

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        return None

    async def stop(self) -> None:
        return None


async def verify_device(dev: DevicePoller, transport: BusLike,
                        count: Callable[[bool], None], say: Say) -> None:
    """Verify ``dev``'s blocks of several fields through ``transport``; what disagrees
    becomes a hole of the device (it is re-planned) and is reported with ``say``."""
    cfg = dev.config
    for block in [b for b in dev.blocks if len(b.fields) > 1]:
        try:
            found = await verify_block(transport, cfg.address, block,
                                       timeout=dev.timeout(transport), retries=cfg.retry_count)
        except BusError as exc:
            say(f"verify-blocks: {cfg.name}: {block}: not verified: {exc}")
            continue
        count(found is not None)
        if found is None:
            continue
        holes = found.holes()
        what = f"block read disagrees with its fields read alone (silent shift): {found}"
        dev.learn_holes(holes, f"silent shift reading {block.table.value} "
                               f"0x{block.address:04X}+{block.count}")
        say(f"verify-blocks: {cfg.name} ({cfg.spec}): {what}; "
            + ("no longer bridged there" if holes else "fields adjacent: nothing to split"))


class RememberHoles(Service):
    """Holes learned per device, kept in ``store`` across runs (profile and variant)."""

    def __init__(self, store: HoleStore, say: Say) -> None:
        self.store, self.say = store, say
        self._loaded: set[int] = set()
        self._saved: dict[int, frozenset[Register]] = {}

    async def start(self, scheduler: Scheduler) -> None:
        for dev in scheduler.pollers():
            if dev.config.profile.variant is None:
                self._load(dev)

    def _load(self, dev: DevicePoller) -> None:
        self._loaded.add(id(dev))
        cfg = dev.config
        known = self.store.get(cfg.name, cfg.profile.id, dev.variant)
        if known and dev.learn_holes(frozenset(known), f"remembered in {self.store.path}"):
            self.say(f"{cfg.name}: not bridging {len(known)} registers learned earlier "
                     f"({self.store.path})")
        self._saved[id(dev)] = frozenset(dev.holes.registers)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        if id(dev) not in self._loaded:
            if dev.variant is None and dev.variant_unknown:
                return  # load what was learned for its variant once it is known
            self._load(dev)
        now = frozenset(dev.holes.registers)
        if now != self._saved.get(id(dev)):
            cfg = dev.config
            try:
                self.store.put(cfg.name, cfg.profile.id, dev.variant, now)
            except OSError as exc:
                self.say(f"cannot write {self.store.path}: {exc.strerror}")
            self._saved[id(dev)] = now

    async def stop(self) -> None:
        return None
