"""A fleet of rtupoll gateways publishing to one local mosquitto.

    .venv/bin/python benchmarks/mqtt_fleet.py [--gateways 10] [--seconds 20] [--baud 9600]

Each gateway is a real ``rtupoll poll --simulate --baud B --interval 0 --mqtt URL``
process: five simulated seed devices on one bus with real wire timing, polled as fast
as the wire allows, each device cycle one JSON state message. One ``mosquitto_sub``
subscribes to every state topic; the gateways run for ``--seconds`` after a warm-up.
Then, in this process, the real ``MqttService`` publishes ``--messages`` state
messages of the same devices to the same broker, one at a time, for the CPU that
publishing alone costs (the fleet's processes also poll and simulate). Prints:

- state messages delivered per second, against the device cycles the gateways
  completed in the same window (their ``--output`` records: 100 % means none lost
  or held back) and against the wire limit (device cycles per second the buses could
  carry at most, without the devices' turnaround: ``poll_common.wire_limit``);
- latency from each reading (``last_seen``: the time its reply was decoded) to the
  subscriber's receipt (``mosquitto_sub`` ``%U``), p50 / p95 / max;
- rtupoll's CPU per published message: in-process (``on_readings`` -> JSON -> outbox
  -> aiomqtt -> socket), and the fleet's whole CPU (polling, simulating, publishing)
  per delivered message;
- the broker's CPU per message, and its share of all the CPU the fleet used.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from poll_common import SEEDS, seed_site, wire_limit

TICK = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu(pids: list[int]) -> float:
    """User + system CPU seconds of these processes (and their threads) so far."""
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / TICK


def percentile(values: list[float], q: float) -> float:
    data = sorted(values)
    return data[max(0, min(len(data) - 1, round(q / 100 * len(data)) - 1))]


def gateways(n: int, baud: int, url: str | None, out: Path) -> list[subprocess.Popen[bytes]]:
    procs = []
    for i in range(n):
        cmd = [sys.executable, "-m", "rtupoll", "poll", "--simulate", "--baud", str(baud),
               "--interval", "0", "--format", "json", "-o", str(out / f"gw{i}.jsonl"), *SEEDS]
        if url:
            cmd += ["--mqtt", f"{url}/gw{i}", "--mqtt-id", f"gw{i}"]
        procs.append(subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
    return procs


def stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        if p.returncode not in (0, -signal.SIGTERM):
            err = p.stderr.read().decode() if p.stderr else ""
            raise SystemExit(f"a gateway failed ({p.returncode}): {err.strip()[-500:]}")


def measure(procs: list[subprocess.Popen[bytes]], seconds: float, warmup: float,
            on_start: object = None) -> float:
    """CPU seconds the gateways spent over ``seconds`` after ``warmup``."""
    time.sleep(warmup)
    pids = [p.pid for p in procs]
    if callable(on_start):
        on_start()
    before = cpu(pids)
    time.sleep(seconds)
    return cpu(pids) - before


async def publish_cpu(url: str, baud: int, messages: int) -> float:
    """CPU seconds per state message published by the real ``MqttService`` (one at a
    time: each is on the socket before the next cycle's readings come)."""
    from rtupoll.config.mqtt_settings import parse_url
    from rtupoll.jobs.scheduler import Scheduler
    from rtupoll.jobs.stats import Reading, State
    from rtupoll.model.interpret import interpret
    from rtupoll.outputs.mqtt import MqttService

    site = seed_site("/dev/null", baud)
    scheduler = Scheduler(site, open_bus=lambda bus: None)  # type: ignore[arg-type,return-value]
    service = MqttService(parse_url(f"{url}/cpu"), site)
    await service.start(scheduler)
    devices = list(scheduler.pollers())
    now = time.time()
    readings = {}
    for d in devices:
        d.stats.state, d.stats.last_good_time = State.ONLINE, now
        readings[d.config.name] = [Reading(now, d.config, f, interpret(f, [i] * f.words))
                                   for i, f in enumerate(d.config.fields)]
    await asyncio.sleep(0.5)  # discovery and the first messages out of the way
    before, sent = time.process_time(), service.published
    for i in range(messages):
        d = devices[i % len(devices)]
        service.outbox.flushed.clear()
        service.on_readings(d, readings[d.config.name])
        await service.outbox.flushed.wait()
    spent, count = time.process_time() - before, service.published - sent
    await service.stop()
    return spent / max(count, 1)


def count_cycles(out: Path, firsts: set[tuple[str, str]], start: float, end: float) -> int:
    """Device cycles the gateways completed in [start, end]: one record of each device's
    first field per cycle, in their ``--output`` files."""
    n = 0
    for path in out.glob("gw*.jsonl"):
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            if (rec["device"], rec["field"]) in firsts and rec["status"] == "ok":
                at = datetime.fromisoformat(rec["time"].replace("Z", "+00:00")).timestamp()
                n += start <= at < end
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gateways", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--messages", type=int, default=5000)
    args = ap.parse_args()

    site = seed_site("/dev/null", args.baud)
    bus = site.buses[0]
    scan = sum(wire_limit(d, bus.framing) for d in bus.devices)
    limit = args.gateways * len(bus.devices) / scan  # device cycles per second, all buses

    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        conf = Path(tmp) / "mosquitto.conf"
        conf.write_text(f"listener {port} 127.0.0.1\npersistence false\nallow_anonymous true\n"
                        "max_queued_messages 100000\n")
        broker = subprocess.Popen(["mosquitto", "-c", str(conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        time.sleep(0.3)
        url = f"mqtt://127.0.0.1:{port}"
        try:
            # the fleet, and a subscriber timing every state message
            sub = subprocess.Popen(["mosquitto_sub", "-h", "127.0.0.1", "-p", str(port),
                                    "-t", "+/+", "-F", "%U %t %p"], stdout=subprocess.PIPE,
                                   text=True, bufsize=1)
            received: list[tuple[float, str, str]] = []

            def pump() -> None:
                assert sub.stdout is not None
                for line in sub.stdout:
                    stamp, topic, body = line.rstrip("\n").split(" ", 2)
                    received.append((float(stamp), topic, body))

            threading.Thread(target=pump, daemon=True).start()
            for old in Path(tmp).glob("gw*.jsonl"):
                old.unlink()
            procs = gateways(args.gateways, args.baud, url, Path(tmp))
            broker_before = [0.0]
            window = [0.0, 0.0]

            def start() -> None:
                window[0] = time.time()
                broker_before[0] = cpu([broker.pid])

            mqtt_cpu = measure(procs, args.seconds, args.warmup, start)
            window[1] = time.time()
            broker_cpu = cpu([broker.pid]) - broker_before[0]
            stop(procs)
            time.sleep(1)
            sub.terminate()
            sub.wait()
            cycles = count_cycles(Path(tmp), {(d.name, d.fields[0].name) for d in bus.devices},
                                  *window)
            one = asyncio.run(publish_cpu(url, args.baud, args.messages))
        finally:
            broker.terminate()
            broker.wait()

    states = [(t, body) for t, topic, body in received if topic.split("/")[1] != "bridge"
              and body.startswith("{") and window[0] <= t < window[1]]
    latencies = []
    for t, body in states:
        seen = json.loads(body).get("last_seen")
        if seen:
            at = datetime.fromisoformat(seen.replace("Z", "+00:00")).timestamp()
            latencies.append((t - at) * 1000)
    n = len(states)
    rate = n / args.seconds
    print(f"{args.gateways} gateways x {len(bus.devices)} devices at {args.baud} baud, "
          f"{args.seconds:g} s measured")
    print(f"state messages delivered: {n} = {rate:.1f}/s, for {cycles} device cycles "
          f"completed ({n / max(cycles, 1):.1%}); wire limit {limit:.1f} device cycles/s -> "
          f"{rate / limit:.1%} of it")
    print(f"latency reading -> subscriber: p50 {percentile(latencies, 50):.1f} ms, "
          f"p95 {percentile(latencies, 95):.1f} ms, max {max(latencies):.1f} ms "
          "(last_seen has millisecond resolution)")
    print(f"rtupoll CPU per published message: {one * 1e6:.0f} µs publishing alone "
          f"({args.messages} messages in-process); the fleet's {mqtt_cpu / args.seconds:.1%} "
          f"of a core = {mqtt_cpu / n * 1e6:.0f} µs per delivered message with polling and "
          "simulating")
    print(f"broker CPU: {broker_cpu / n * 1e6:.0f} µs per message, "
          f"{broker_cpu / args.seconds:.1%} of a core = "
          f"{broker_cpu / (broker_cpu + mqtt_cpu):.1%} of all the CPU the fleet used")


if __name__ == "__main__":
    main()
