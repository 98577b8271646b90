"""Memory of ``rtupoll poll`` on 66 devices on 6 buses, against a bare pymodbus poller.

Six simulators (``rtupoll simulate --baud 115200``, each in its own process, a pty
each) serve 11 devices apiece, the three seed profiles that run at 115200 baud
(radar, Huiwen, CO2Meter) in turn at addresses 1-11. Two pollers read every device's
default fields once a second, one after the other against the same simulators:

- rtupoll: ``rtupoll poll -c SITE --format json -o FILE``, a site file of six buses;
- peer: a bare pymodbus poller, one ``AsyncModbusSerialClient`` per bus, reading the
  same planned blocks in a loop once a second (no decoding, no output): the least a
  Python poller on the same library holds.

After ``--seconds`` of polling each process's resident memory (VmRSS, and its peak
VmHWM) is read from /proc; the figure is rtupoll's over the peer's (the goal: at most
1.1), per round and as the median.

Both run on one interpreter: a plain install of rtupoll, as users have it (the venv
``read_vs_mbpoll.plain_install`` builds, its dependencies this environment's), with
bytecode caching on (an installed package has its .pyc files, as the peer's pymodbus
has; with PYTHONDONTWRITEBYTECODE the checkout's modules would be compiled at every
start, and the compiler's transient memory stays in the process's RSS), after a
warm-up poll that fills the profile cache (a temporary one). ``--checkout`` runs
rtupoll from this checkout's editable install instead, with the environment as it is.

Run: .venv/bin/python benchmarks/poll_rss.py [--seconds 20] [--rounds 2] [--checkout]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from poll_common import seed_site, simulator
from read_vs_mbpoll import plain_install

from rtupoll.model.planner import plan

PROFILES = ("radar-level", "huiwen-aq", "co2meter-an117")
BUSES, PER_BUS, BAUD = 6, 11, 115200

PEER = r'''
import asyncio, json, sys
from pymodbus.client import AsyncModbusSerialClient

async def bus(port, baud, reads):
    client = AsyncModbusSerialClient(port, baudrate=baud, timeout=0.5, retries=0)
    await client.connect()
    calls = {"holding": client.read_holding_registers, "input": client.read_input_registers,
             "coil": client.read_coils, "discrete": client.read_discrete_inputs}
    while True:
        start = asyncio.get_running_loop().time()
        for unit, table, address, count in reads:
            reply = await calls[table](address, count=count, device_id=unit)
            assert not reply.isError(), reply
        await asyncio.sleep(max(0.0, 1.0 - (asyncio.get_running_loop().time() - start)))

async def main():
    spec = json.loads(sys.argv[1])
    await asyncio.gather(*(bus(port, spec["baud"], reads) for port, reads in spec["buses"]))

asyncio.run(main())
'''


def devices(bus: int) -> list[str]:
    return [f"{PROFILES[(bus + i) % len(PROFILES)]}@{i + 1}" for i in range(PER_BUS)]


def site_yaml(ports: list[str]) -> str:
    lines = ["buses:"]
    for b, port in enumerate(ports):
        lines += [f"  - name: bus{b + 1}", f"    port: {port}", f"    baudrate: {BAUD}",
                  "    devices:"]
        for d in devices(b):
            pid, _, address = d.partition("@")
            lines.append(f"      - {{name: bus{b + 1}-{pid}-{address}, profile: {pid}, "
                         f"address: {address}, interval: 1}}")
    return "\n".join(lines) + "\n"


def planned_reads(ports: list[str]) -> list[tuple[str, list[tuple[int, str, int, int]]]]:
    """Each bus's blocks, as the planner makes them for rtupoll (the peer reads the same)."""
    out = []
    for b, port in enumerate(ports):
        site = seed_site(port, BAUD, devices(b))
        reads = [(d.address, block.table.value, block.address, block.count)
                 for _, d in site.devices() for block in plan(d.fields, d.profile)]
        out.append((port, reads))
    return out


def memory(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a running process, in MB."""
    status = dict(line.split(":", 1) for line in
                  Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return (int(status["VmRSS"].split()[0]) / 1024, int(status["VmHWM"].split()[0]) / 1024)


def run_for(argv: list[str], seconds: float, out: Path | None = None,
            env: dict[str, str] | None = None) -> tuple[float, float]:
    with contextlib.ExitStack() as stack:
        sink = stack.enter_context(out.open("w")) if out else subprocess.DEVNULL
        proc = subprocess.Popen(argv, stdout=sink, stderr=subprocess.PIPE, env=env)
        try:
            time.sleep(seconds)
            if proc.poll() is not None:
                err = proc.stderr.read().decode() if proc.stderr else ""
                raise SystemExit(f"{argv[:4]} stopped: {err.strip()[-2000:]}")
            return memory(proc.pid)
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="polling before the reading")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--before", metavar="PYTHON",
                    help="also poll with this interpreter's rtupoll (another checkout's venv) "
                         "in each round: before and after in the same run")
    ap.add_argument("--checkout", action="store_true",
                    help="run rtupoll from this checkout (editable install, environment as "
                         "it is), not from a plain install with bytecode caching")
    args = ap.parse_args()
    ratios, ours, theirs, before = [], [], [], []
    with contextlib.ExitStack() as stack:
        ports = [stack.enter_context(simulator(BAUD, devices(b))) for b in range(BUSES)]
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        site = tmp / "site.yaml"
        site.write_text(site_yaml(ports))
        spec = json.dumps({"baud": BAUD, "buses": planned_reads(ports)})
        python, env = Path(sys.executable), None
        if not args.checkout:
            env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
            env["XDG_CACHE_HOME"] = str(tmp / "cache")  # its own profile cache
            python = plain_install(tmp / "venv", env)
            run_for([str(python), "-m", "rtupoll", "poll", "-c", str(site), "--format", "json",
                     "-o", str(tmp / "warm-up.jsonl")], 3.0, env=env)
        for r in range(args.rounds):
            peer = run_for([str(python), "-c", PEER, spec], args.seconds, env=env)
            records = tmp / f"readings{r}.jsonl"
            mine = run_for([str(python), "-m", "rtupoll", "poll", "-c", str(site),
                            "--format", "json", "-o", str(records)], args.seconds, env=env)
            polled = {json.loads(line)["device"] for line in records.read_text().splitlines()}
            if len(polled) != BUSES * PER_BUS:
                raise SystemExit(f"rtupoll polled {len(polled)} devices, not {BUSES * PER_BUS}")
            ours.append(mine)
            theirs.append(peer)
            ratios.append(mine[0] / peer[0])
            print(f"round {r + 1}: rtupoll {mine[0]:.1f} MB (peak {mine[1]:.1f}), peer "
                  f"{peer[0]:.1f} MB (peak {peer[1]:.1f}): x{ratios[-1]:.2f}", flush=True)
            if args.before:
                then = run_for([args.before, "-m", "rtupoll", "poll", "-c", str(site),
                                "--format", "json", "-o", str(tmp / "before.jsonl")],
                               args.seconds, env=env)
                before.append(then[0] / peer[0])
                print(f"  before: rtupoll {then[0]:.1f} MB (peak {then[1]:.1f}): "
                      f"x{before[-1]:.2f}", flush=True)
    print(f"\n{BUSES * PER_BUS} devices on {BUSES} buses at {BAUD} baud, after "
          f"{args.seconds:g} s of polling: rtupoll {statistics.median(m[0] for m in ours):.1f} "
          f"MB, the bare pymodbus poller {statistics.median(p[0] for p in theirs):.1f} MB; "
          f"ratio min x{min(ratios):.2f}, median x{statistics.median(ratios):.2f}"
          + (f"; before: median x{statistics.median(before):.2f}" if before else ""))


if __name__ == "__main__":
    main()
