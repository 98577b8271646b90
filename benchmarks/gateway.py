"""The Modbus TCP gateway: a client's added latency against the wire, and what a
hammering client costs the poller -- measured in one run.

The simulator runs as ``rtupoll simulate --baud N`` in its own process (turnaround 0),
and so does the Modbus TCP client (pymodbus's plain synchronous client, reading the
Huiwen module's four input registers at 30006 in a loop), so the gateway's process
does only the gateway's and the poller's work. Five phases on the same simulator:

0. bare: the least any master could take on this rig: a few lines of ``os.write`` and
   ``select`` on the pty, the request sent exactly 3.5 characters after the last reply
   byte arrived, the reply read by its known length (no checks, no event loop): the
   transactions/s the simulator and the pty allow, against the wire limit;
1. direct: rtupoll's own bus reads the same four registers (no gateway): the floor
   rtupoll's RTU master sets on this machine;
2. gateway alone (``poll --serve`` with no devices): the client's latency through
   the gateway, against the transaction's wire time and against the direct read;
3. poller alone: three devices at interval 0 (the bus saturated): its transactions/s;
4. poller and the hammering client together: both rates, and the client's latency.

Run: .venv/bin/python benchmarks/gateway.py [--baud 9600] [--seconds 8]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import os
import select
import statistics
import subprocess
import sys
import termios
import time
import tty

from poll_common import simulator

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.site import BusConfig, Site, from_specs
from rtupoll.gateway.service import GatewayService
from rtupoll.io.bus import Bus, PortSettings
from rtupoll.jobs.scheduler import DevicePoller, Scheduler
from rtupoll.jobs.stats import Reading
from rtupoll.rtu import Framing, Table, transaction_wire_time
from rtupoll.rtu.messages import ReadRequest

DEVICES = ("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3")
UNIT, ADDRESS, COUNT = 3, 0x7536, 4  # Huiwen: PM2.5, TVOC, HCHO, CO2


def client(port: int, seconds: float) -> None:
    """The hammering client (a child process): latencies in seconds, as JSON on stdout."""
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    assert c.connect()
    lat: list[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t = time.monotonic()
        r = c.read_input_registers(ADDRESS, count=COUNT, device_id=UNIT)
        if r.isError() or len(r.registers) != COUNT:
            raise SystemExit(f"client: bad answer {r}")
        lat.append(time.monotonic() - t)
    c.close()
    print(json.dumps(lat))


def bare(port: str, baud: int, n: int) -> tuple[float, float]:
    """A bare master on the pty, ``n`` transactions in a row: (median, mean) seconds from
    one request's write to the next's (the mean as the client's answers/s count it)."""
    request = ReadRequest(UNIT, Table.INPUT.read_function, ADDRESS, COUNT).frame()
    length, silence = 5 + 2 * COUNT, Framing(baud).silence
    fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)  # at the bus's speed (the simulator checks it)
        attrs[4] = attrs[5] = getattr(termios, f"B{baud}")
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        termios.tcflush(fd, termios.TCIOFLUSH)
        last, writes = time.monotonic(), []
        for _ in range(n + 1):
            while (wait := last + silence - time.monotonic()) > 0:
                if select.select([fd], [], [], wait)[0]:  # a stray byte: silence again
                    os.read(fd, 256)
                    last = time.monotonic()
            writes.append(time.monotonic())
            os.write(fd, request)
            got = b""
            while len(got) < length:
                if not select.select([fd], [], [], 0.5)[0]:
                    raise SystemExit("bare master: no reply")
                got += os.read(fd, 256)
            last = time.monotonic()
        cycles = [b - a for a, b in itertools.pairwise(writes)]
        return statistics.median(cycles), statistics.mean(cycles)
    finally:
        os.close(fd)


async def direct(port: str, baud: int, n: int) -> list[float]:
    lat = []
    async with Bus(PortSettings(port, baud)) as bus:
        for _ in range(n):
            t = time.monotonic()
            await bus.read(UNIT, Table.INPUT, ADDRESS, COUNT, timeout=0.5)
            lat.append(time.monotonic() - t)
    return lat


async def served(site: Site, seconds: float, hammer: bool) -> tuple[Scheduler, list[float]]:
    scheduler = Scheduler(site)
    service = GatewayService()

    def sink(dev: DevicePoller, readings: list[Reading]) -> None:
        bad = [r for r in readings if not r.ok]
        if bad:
            raise SystemExit(f"{dev.config.name}: {bad[0].field.name}: {bad[0].status.value}: "
                             f"{bad[0].error}")

    stop = asyncio.Event()
    await scheduler.open()
    await service.start(scheduler)
    port = service.gateways[0].address[1]
    task = asyncio.create_task(scheduler.run(sink, stop))
    lat: list[float] = []
    try:
        if hammer:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, __file__, "--client", str(port), "--seconds", str(seconds),
                stdout=subprocess.PIPE)
            out, _ = await proc.communicate()
            lat = json.loads(out)
        else:
            await asyncio.sleep(seconds)
    finally:
        stop.set()
        await task
        await service.stop()
        await scheduler.close()
    return scheduler, lat


def requests(s: Scheduler) -> int:
    return sum(d.stats.requests for d in s.pollers())


def ms(x: float) -> str:
    return f"{x * 1000:.1f} ms"


def run(baud: int, seconds: float) -> None:
    framing = Framing(baud)
    wire = transaction_wire_time(framing, 8, 5 + 2 * COUNT)
    serve = ServeConfig("127.0.0.1", 0)
    with simulator(baud, DEVICES) as port:
        floor, floor_mean = bare(port, baud, 300)
        d = asyncio.run(direct(port, baud, 100))
        gw_only = Site((BusConfig("gw", port, baud, serve=serve),))
        _, alone = asyncio.run(served(gw_only, seconds, hammer=True))
        specs = [(x.split("@")[0], int(x.split("@")[1])) for x in DEVICES]
        site = from_specs(port, specs, baudrate=baud, interval=0, check_serial=False)
        site = Site((BusConfig(**{**site.buses[0].__dict__, "serve": serve}),))
        poller_only, _ = asyncio.run(served(site, seconds, hammer=False))
        shared, both = asyncio.run(served(site, seconds, hammer=True))
    med_d, med_g = statistics.median(d), statistics.median(alone)
    print(f"{baud} baud; transaction (FC04, 4 registers) on the wire with two silences: "
          f"{ms(wire)}")
    print(f"bare master (os.write and select on the pty, silence kept): median {ms(floor)} "
          f"per transaction = {wire / floor:.2f} of the wire limit (mean {ms(floor_mean)}: "
          f"{1 / floor_mean:.1f}/s, {wire / floor_mean:.2f})")
    print(f"direct read (rtupoll's bus, no gateway): median {ms(med_d)} = "
          f"{med_d / wire:.2f}x the wire time")
    print(f"through the gateway (pymodbus TCP client, no poller): median {ms(med_g)} = "
          f"{med_g / wire:.2f}x the wire time; added by the gateway over the direct read: "
          f"{ms(med_g - med_d)}")
    a = len(alone) / seconds
    print(f"answers/s through the gateway (one client, no poller): {a:.1f} = {a * wire:.2f} "
          f"of the silence-keeping wire limit ({1 / wire:.1f}/s), {a * floor_mean:.2f} of the "
          "bare master's")
    r0 = requests(poller_only) / seconds
    r1 = requests(shared) / seconds
    c1 = len(both) / seconds
    print(f"poller alone (3 devices, interval 0): {r0:.1f} transactions/s")
    print(f"poller with a hammering client: {r1:.1f} transactions/s "
          f"({r1 / r0:.0%} of alone); the client got {c1:.1f} requests/s, latency p50 "
          f"{ms(statistics.median(both))}, p95 {ms(sorted(both)[int(0.95 * len(both))])}; "
          f"line shared {r1 / (r1 + c1):.0%} poller / {c1 / (r1 + c1):.0%} client")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--client", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.client is not None:
        client(args.client, args.seconds)
        return
    with contextlib.suppress(KeyboardInterrupt):
        run(args.baud, args.seconds)


if __name__ == "__main__":
    main()
