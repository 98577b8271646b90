"""Instructions per transaction of ``rtupoll poll``, against another version, in one run.

CPU time on a shared machine drifts by ±10 % a round (``poll_cpu.py``), so a cost of
a few percent is measured here in instructions, which the load does not change: the
real command (``rtupoll poll --format json`` to a file, the three 115200-baud seed
devices at ``--interval 0``, the simulator in its own process) runs under valgrind's
callgrind; once it has written its first records (start-up is paid once per process)
the counters are zeroed, and after ``--seconds`` of polling dumped
(``callgrind_control -z``, ``-d``): the instructions executed in that window are
divided by the transactions the records show. ``--baseline SRC`` runs the same from
another source tree (e.g. ``git archive REV src``) against the same simulator, the two
alternating for ``--rounds``. The timeout is pinned (``--timeout 1``): under valgrind
the poller runs some 50 times slower, and a learned timeout would time out replies the
simulator sent at once.

Run: .venv/bin/python benchmarks/poll_instructions.py --baseline /tmp/base/src
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from poll_common import seed_site, simulator, transactions_of

DEVICES = ("radar-level@2", "huiwen-aq@3", "co2meter-an117@4")


def measure(port: str, baud: int, seconds: float, source: str | None) -> tuple[int, int]:
    """(instructions, transactions) of the command in a steady window."""
    site = seed_site(port, baud, DEVICES)
    transactions = transactions_of(site)

    with tempfile.TemporaryDirectory() as tmp:
        out, profile = Path(tmp) / "readings.jsonl", Path(tmp) / "callgrind.out"
        env = dict(os.environ)
        if source is not None:
            env["PYTHONPATH"] = source
        with out.open("w") as fh:
            proc = subprocess.Popen(
                ["valgrind", "--tool=callgrind", f"--callgrind-out-file={profile}",
                 sys.executable, "-m", "rtupoll", "poll",
                 "--port", port, "--baudrate", str(baud), "--interval", "0", "--timeout", "1",
                 "--format", "json", *DEVICES],
                stdout=fh, stderr=subprocess.PIPE, env=env)
            try:
                deadline = time.monotonic() + 300
                while len(out.read_text().splitlines()) < 300:
                    if proc.poll() is not None or time.monotonic() > deadline:
                        raise SystemExit("rtupoll poll did not start polling under valgrind")
                    time.sleep(0.2)
                subprocess.run(["callgrind_control", "-z", str(proc.pid)], check=True,
                               capture_output=True)
                lines0 = out.read_text().splitlines()
                time.sleep(seconds)
                subprocess.run(["callgrind_control", "-d", str(proc.pid)], check=True,
                               capture_output=True)
                lines1 = out.read_text().splitlines()
            finally:
                proc.send_signal(signal.SIGINT)
                proc.communicate(timeout=300)
        dumps = sorted(Path(tmp).glob("callgrind.out.*"))  # the window's: .1
        if not dumps:
            raise SystemExit("callgrind wrote no dump for the window")
        text = dumps[0].read_text(errors="replace")
    found = re.search(r"^(?:summary|totals):\s+(\d+)", text, re.M)
    if found is None:
        raise SystemExit("no instruction count in callgrind's output")
    return int(found.group(1)), transactions(lines1) - transactions(lines0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--seconds", type=float, default=20.0, help="instrumented, per run")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--baseline", metavar="SRC", help="another version's src/ tree")
    args = ap.parse_args()
    names = {"this": None, "baseline": args.baseline} if args.baseline else {"this": None}
    per_tx: dict[str, list[float]] = {name: [] for name in names}
    with simulator(args.baud, DEVICES) as port:
        for r in range(args.rounds):
            order = list(names) if r % 2 == 0 else list(reversed(names))
            for name in order:
                ir, tx = measure(port, args.baud, args.seconds, names[name])
                per_tx[name].append(ir / tx)
                print(f"round {r + 1}: {name}: {ir / 1e6:.1f} M instructions, {tx} "
                      f"transactions, {ir / tx / 1e3:.0f} k per transaction", flush=True)
    this = statistics.median(per_tx["this"])
    print(f"\nthis version: {this / 1e3:.0f} k instructions per transaction (median)")
    if args.baseline:
        base = statistics.median(per_tx["baseline"])
        print(f"{args.baseline}: {base / 1e3:.0f} k; this against it: x{this / base:.3f}")


if __name__ == "__main__":
    main()
