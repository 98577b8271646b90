"""``read``'s start-up on Windows: the official CPython 3.13 (win_amd64) under Wine, against
the same interpreter's ``python -c "import click, serial"`` (the libraries' floor).

scripts/windows-setup's runtime (.venv-windows: the embeddable CPython, rtupoll's wheel
and the dependencies' Windows wheels unpacked into its site-packages); one Wine server
kept for the run, COM5 mapped to a simulated Huiwen module's pty. Interleaved, N runs
each: ``python.exe -c pass``, the floor, and ``python.exe -m rtupoll read -p COM5
--format json huiwen-aq@1 co2`` (checked: the pinned value), after one warm-up run of
each (it writes the .pyc files and the profile cache, as a user's first read does).
Wall time from the start of the Wine process to its end, as a user waits for it (CPU
is not shown: the wineserver does part of each process's work, in its own process).
With ``--importtime`` it also prints the modules a read imports beyond the floor's, with
their own import times (``python -X importtime``): where the time goes.

Run from the repository root::

    .venv/bin/python benchmarks/windows_startup.py [--runs 15] [--importtime]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "windows"))

from wine import ENCODING, Wine, environment, setup  # noqa: E402

from rtupoll.sim.runner import simulated_bus  # noqa: E402

READ = ["-m", "rtupoll", "read", "-p", "COM5", "--format", "json", "huiwen-aq@1", "co2"]
CASES = {
    "python -c pass": ["-c", "pass"],
    "the floor: import click, serial": ["-c", "import click, serial"],
    "rtupoll read": READ,
}


def run(wine: Wine, args: list[str]) -> tuple[float, str]:
    """(wall s, stdout) of one run."""
    start = time.perf_counter()
    proc = subprocess.run(wine.argv(*args), stdin=subprocess.DEVNULL, capture_output=True,
                          env=environment(), encoding=ENCODING, timeout=120)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed ({proc.returncode}): {proc.stderr[-800:]}")
    return wall, proc.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=15, help="runs of each (default 15)")
    ap.add_argument("--importtime", action="store_true",
                    help="also show the slowest imports of one read (-X importtime)")
    args = ap.parse_args()
    setup()
    with tempfile.TemporaryDirectory() as tmp:
        link = Path(tmp) / "com5"
        with simulated_bus(["huiwen-aq@1"], tick=None, link=str(link)) as sim, \
                Wine(ports={"COM5": link}) as wine:
            sim.set(1, "co2", 812)
            walls: dict[str, list[float]] = {name: [] for name in CASES}
            for case in CASES.values():  # warm-up: bytecode, the profile cache
                run(wine, case)
            for _ in range(args.runs):
                for name, case in CASES.items():
                    wall, out = run(wine, case)
                    walls[name].append(wall)
                    if case is READ:
                        assert json.loads(out)["value"] == 812, out
            floor = statistics.median(walls["the floor: import click, serial"])
            print(f"Windows CPython 3.13 under Wine, {args.runs} runs each, interleaved "
                  "(median, min-max wall):")
            for name, times in walls.items():
                median = statistics.median(times)
                print(f"  {name:34} {median * 1000:7.1f} ms  ({min(times) * 1000:.0f}-"
                      f"{max(times) * 1000:.0f})  x{median / floor:.2f} the floor")
            read = statistics.median(walls["rtupoll read"])
            print(f"read / floor: x{read / floor:.2f} (target <= x1.3); read beyond the "
                  f"floor: {(read - floor) * 1000:.0f} ms")
            if args.importtime:
                read, floor_imports = importtime(wine, READ), importtime(
                    wine, CASES["the floor: import click, serial"])
                beyond = {name: t for name, t in read.items() if name not in floor_imports}
                print(f"-X importtime: the read imports {len(read)} modules, "
                      f"{sum(read.values()) / 1000:.0f} ms of import (self times); "
                      f"{len(beyond)} of them the floor does not, "
                      f"{sum(beyond.values()) / 1000:.0f} ms; the largest of those (ms):")
                for name, t in sorted(beyond.items(), key=lambda kv: -kv[1])[:15]:
                    print(f"  {t / 1000:6.1f}  {name}")


def importtime(wine: Wine, args: list[str]) -> dict[str, int]:
    """Each module's own import time (us) in one run, ``python -X importtime``."""
    proc = subprocess.run(wine.argv("-X", "importtime", *args), capture_output=True,
                          stdin=subprocess.DEVNULL, env=environment(), encoding=ENCODING,
                          timeout=120)
    times = {}
    for line in proc.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            own, _, name = line[len("import time:"):].split("|", 2)
            if own.strip().isdigit():
                times[name.strip()] = int(own)
    return times

if __name__ == "__main__":
    main()
