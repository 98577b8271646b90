"""Time a full 1-247 scan sweep against the floor its own timeouts set.

A sweep is dominated by empty addresses, each costing one derived timeout (request
and reply wire time, the inter-frame silence, the turnaround margin) plus the silence
before the next request. This runs the real sweep (``rtupoll.jobs.scan.sweep`` through
``bus.Bus`` and pymodbus) against the simulator on a pty, at a simulated wire speed,
with the five seed devices on the bus, and prints the measured time next to:

- floor: every empty address at exactly its timeout, and every request to a live
  device at its wire time + two silences, or its timeout when the device ignores it
  (no device turnaround, no CPU);
- overhead: measured / floor.

Run: .venv/bin/python benchmarks/scan_sweep.py [--baud 9600,115200] [--addresses 1-247]
"""

from __future__ import annotations

import argparse
import asyncio
import time

from rtupoll.config.library import load_library
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.jobs.scan import (
    Found,
    Setting,
    default_margin,
    parse_addresses,
    presence_probes,
    probe_timeout,
    skipped,
    sweep,
)
from rtupoll.rtu import Framing, transaction_wire_time
from rtupoll.sim.runner import simulated_bus

SEEDS = ["net-irnet-pro@3", "radar-level@7", "huiwen-aq@12", "co2meter-an117@20",
         "banner-ez-array@31"]


def run(baud: int, addresses: str) -> None:
    library = sorted(load_library().profiles.values(), key=lambda p: p.id)
    wanted = parse_addresses(addresses)
    units = [a for a in wanted if a not in skipped(wanted, library)]
    probes, margin = presence_probes(library), default_margin(library)
    setting, framing = Setting(baud), Framing(baud)
    with simulated_bus(SEEDS, baudrate=baud) as sim:
        def open_bus(s: Setting) -> Bus:
            return Bus(PortSettings(sim.port, s.baudrate, deassert_dtr=True), drain=0.0)

        found: list[Found] = []
        started = time.monotonic()
        asyncio.run(sweep(open_bus, [setting], units, library, margin=margin, probes=probes,
                          found=found))
        elapsed = time.monotonic() - started
        wire = sim.wire
    answered = {w.data[0] for w in wire if w.direction == "out"}
    dead = [a for a in units if a not in answered]
    per_dead = sum(probe_timeout(framing, n, margin) for *_, n in probes)
    # each request to a live device: its exchange on the wire, or a timeout if ignored
    live, live_requests = 0.0, 0
    for i, w in enumerate(wire):
        if w.direction != "in" or w.data[0] not in answered:
            continue
        live_requests += 1
        reply = wire[i + 1] if i + 1 < len(wire) and wire[i + 1].direction == "out" else None
        live += transaction_wire_time(framing, len(w.data), len(reply.data)) if reply \
            else probe_timeout(framing, 1, margin)
    floor = len(dead) * per_dead + live
    ids = ", ".join(f"{f.address}={f.profile.id if f.profile else f.status}" for f in found)
    print(f"{baud:>6} baud: {len(units)} addresses ({len(dead)} empty, {len(answered)} "
          f"answering) in {elapsed:6.2f} s; floor {floor:6.2f} s "
          f"(empty: {1000 * per_dead:.1f} ms each; {live_requests} requests to live "
          f"devices); overhead x{elapsed / floor:.2f}")
    print(f"             identified: {ids}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baud", default="9600,115200")
    parser.add_argument("--addresses", default="1-247")
    args = parser.parse_args()
    for baud in (int(b) for b in args.baud.split(",")):
        run(baud, args.addresses)


if __name__ == "__main__":
    main()
