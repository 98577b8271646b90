"""Start-up cost of a one-shot read: ``rtupoll read --format json`` against ``mbpoll``.

Both tools read the same register (the Huiwen module's CO2, input 30009, sent as
0x7539) from the same simulated device, in the same run, N times each; the script
prints each tool's median wall time and the ratio, and checks that both read the same
value. mbpoll is a small C program, so the ratio is mostly the Python interpreter and
the imports a read needs (click, pyserial): what this measures is
whether rtupoll pays for anything more (the simulator, rich, the scheduler).

Run from the repository root::

    .venv/bin/python benchmarks/read_vs_mbpoll.py            # 20 runs each
    .venv/bin/python benchmarks/read_vs_mbpoll.py --runs 50 --baud 9600

rtupoll runs from a plain install, as users have it: the script builds one
(``pip install --no-deps .`` into a temporary venv whose dependencies are this
environment's), because the development checkout's editable install adds its own
import hook to every start. Next to the two tools it times the floor any Python tool
built on the same libraries pays before doing anything: the interpreter importing
click and pyserial (what a one-shot read uses: it reads on the blocking bus,
``rtupoll.io.syncbus``, with no event loop and no pymodbus), from
the same install.

Bytecode caching is switched on for the child processes (and one warm-up run made),
because an installed package has its .pyc files; an environment with
PYTHONDONTWRITEBYTECODE would otherwise recompile every module on every run. The
warm-up also fills the profile cache (a temporary one), as a user's first read does;
the same read without it (``RTUPOLL_NO_PROFILE_CACHE=1``) is timed beside it.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

from rtupoll.sim.runner import simulated_bus

DEVICE = "huiwen-aq@1"
FIELD, REFERENCE, VALUE = "co2", 30009, 612


def timed(argv: list[str], env: dict[str, str]) -> tuple[float, str]:
    start = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=30)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{argv[0]} failed ({proc.returncode}): {proc.stderr.strip()}")
    return elapsed, proc.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs of each tool (default 20)")
    ap.add_argument("--baud", type=int, default=None,
                    help="simulate wire timing at this baud rate (default: none)")
    args = ap.parse_args()
    mbpoll = shutil.which("mbpoll")
    if mbpoll is None:
        raise SystemExit("mbpoll is not installed (scripts/setup --test installs it)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as tmp:
        env["XDG_CACHE_HOME"] = str(Path(tmp) / "cache")  # its own profile cache
        python = plain_install(Path(tmp) / "venv", env)
        measure(args, env, mbpoll, python)


def plain_install(venv: Path, env: dict[str, str], root: Path | None = None) -> Path:
    """A venv with rtupoll installed from this checkout (or ``root``) as a wheel; its
    dependencies are this environment's (a .pth line), so nothing is downloaded but the
    build backend."""
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; "
                              "print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    (Path(purelib) / "rtupoll-deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    root = root or Path(__file__).resolve().parents[1]
    built = subprocess.run([str(python), "-m", "pip", "install", "-q", "--no-deps", str(root)],
                           capture_output=True, text=True, env=env)
    if built.returncode:
        raise SystemExit(f"could not install rtupoll into a venv: {built.stderr.strip()}")
    return python


def measure(args: argparse.Namespace, env: dict[str, str], mbpoll: str, python: Path) -> None:
    rtupoll = [str(python.parent / "rtupoll")]
    with simulated_bus([DEVICE], sets=[f"{DEVICE}.{FIELD}={VALUE}"], baudrate=args.baud,
                       tick=None) as sim:
        ours = [*rtupoll, "read", "--port", sim.port, "--format", "json", DEVICE, FIELD]
        theirs = [mbpoll, "-m", "rtu", "-b", str(args.baud or 9600), "-P", "none", "-a", "1",
                  "-t", "3", "-r", str(REFERENCE), "-0", "-c", "1", "-1", sim.port]
        bare = [str(python), "-c", "pass"]
        floor = [str(python), "-c", "import click, serial"]
        uncached = {**env, "RTUPOLL_NO_PROFILE_CACHE": "1"}
        timed(ours, env)  # warm-up: writes the .pyc files and the profile cache
        times: dict[str, list[float]] = {"rtupoll": [], "uncached": [], "mbpoll": [],
                                         "python": [], "floor": []}
        for _ in range(args.runs):  # interleaved, so drift hits both alike
            t, out = timed(ours, env)
            assert f'"value":{VALUE}' in out, out
            times["rtupoll"].append(t)
            t, out = timed(ours, uncached)
            assert f'"value":{VALUE}' in out, out
            times["uncached"].append(t)
            t, out = timed(theirs, env)
            assert re.search(rf"\[{REFERENCE}\]:\s+{VALUE}\b", out), out
            times["mbpoll"].append(t)
            times["python"].append(timed(bare, env)[0])
            times["floor"].append(timed(floor, env)[0])

    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"one-shot read of {DEVICE} {FIELD} (input {REFERENCE}), {args.runs} runs each, "
          f"wire timing {'at ' + str(args.baud) + ' baud' if args.baud else 'off'}")
    print(f"  rtupoll read --format json  median {med['rtupoll'] * 1000:7.1f} ms")
    print(f"    the same, no profile cache  median {med['uncached'] * 1000:7.1f} ms  "
          "(RTUPOLL_NO_PROFILE_CACHE=1: PyYAML imported, the profile parsed)")
    print(f"  mbpoll                      median {med['mbpoll'] * 1000:7.1f} ms")
    print(f"  python -c pass (baseline)   median {med['python'] * 1000:7.1f} ms")
    print(f"  the libraries' floor        median {med['floor'] * 1000:7.1f} ms  "
          "(python importing click and pyserial)")
    pairs = sorted(a / b for a, b in zip(times["rtupoll"], times["mbpoll"], strict=True))
    print(f"  rtupoll / mbpoll run by run: min {pairs[0]:.2f}x, median "
          f"{statistics.median(pairs):.2f}x, max {pairs[-1]:.2f}x")
    print(f"  ratio rtupoll / mbpoll: {med['rtupoll'] / med['mbpoll']:.1f}x "
          f"({med['uncached'] / med['mbpoll']:.1f}x without the profile cache); the floor alone: "
          f"{med['floor'] / med['mbpoll']:.1f}x; rtupoll beyond the floor: "
          f"{(med['rtupoll'] - med['floor']) * 1000:.1f} ms")


if __name__ == "__main__":
    main()
