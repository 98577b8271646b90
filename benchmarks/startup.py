"""Start-up cost of every command: CPU, wall time and peak memory of one short run each.

Each command runs once the way a user (or the test suite, ~285 starts a run) runs it,
against a simulated bus on a pty, from a plain install of this checkout (as
``read_vs_mbpoll.py`` builds it: ``pip install --no-deps .`` into a temporary venv),
interleaved with ``python -c pass`` and the libraries' floor (``import click, serial``)
from the same install. With ``--before REV`` the same commands run, interleaved, from
a plain install of that git revision too, so before and after are one run's figures.

Run from the repository root::

    .venv/bin/python benchmarks/startup.py                     # 7 runs each
    .venv/bin/python benchmarks/startup.py --before main --runs 11
    .venv/bin/python benchmarks/startup.py --editable --only read   # the editable install

CPU is the child's user + system time (``os.wait4``), the figure that does not grow with
other processes' load as wall time does; peak memory is its maximum resident set
(``/usr/bin/time``). ``simulate``
is timed from its start until it says it serves (then interrupted): its start-up.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from read_vs_mbpoll import plain_install

from rtupoll.sim.runner import simulated_bus

ROOT = Path(__file__).resolve().parents[1]
DEVICES = ["huiwen-aq@1", "xy-md02@2"]
# also timed with RTUPOLL_NO_PROFILE_CACHE=1: one profile, and all 24 bundled ones
UNCACHED = ("read", "profiles list")


def commands(port: str) -> dict[str, list[str]]:
    """Each command's argv after ``rtupoll``: one short, real run."""
    return {
        "read": ["read", "--port", port, "--format", "json", "huiwen-aq@1", "co2"],
        "read (table)": ["read", "--port", port, "huiwen-aq@1", "co2"],
        "poll --once": ["poll", "--once", "--port", port, "--format", "json", "huiwen-aq@1"],
        "write": ["write", "-y", "--format", "json", "--port", port, "xy-md02@2",
                  "temperature_correction=0"],
        "set-address --dry-run": ["set-address", "--port", "/dev/null", "--dry-run",
                                  "radar-level@1", "11"],
        "scan": ["scan", "--port", port, "--addresses", "1-2", "--baudrate", "9600",
                 "--format", "json"],
        "guess": ["guess", "--port", port, "--address", "1", "--format", "json",
                  "input:30009:2"],
        "decode": ["decode", "01030000000AC5CD"],
        "sniff": ["sniff", "--port", port, "--baudrate", "9600", "--duration", "0.05",
                  "--format", "json"],
        "profiles list": ["profiles", "list", "--format", "json"],
        "profiles show": ["profiles", "show", "huiwen-aq"],
        "--help": ["--help"],
        "simulate": ["simulate", "huiwen-aq@1"],
    }


def run(argv: Sequence[str], env: dict[str, str]) -> tuple[float, float, float]:
    """(CPU s, wall s, peak RSS MiB) of one run; ``simulate`` until it serves."""
    # the peak memory from /usr/bin/time: a child forked from this (large) process would
    # count the pages it held of this one before exec as its own
    with tempfile.NamedTemporaryFile("r", prefix="startup-rss-") as rss:
        cpu, wall = _run(["/usr/bin/time", "-f", "%M", "-o", rss.name, *argv], env)
        return cpu, wall, int(rss.read().split()[-1]) / 1024


def _run(argv: Sequence[str], env: dict[str, str]) -> tuple[float, float]:
    serving = "simulate" in argv[6:7]
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                            text=True, start_new_session=True)
    out = ""
    assert proc.stdout is not None and proc.stderr is not None
    if serving:
        for line in proc.stdout:
            out += line
            if line.startswith("Press Ctrl-C"):
                break
        wall = time.perf_counter() - start
        os.killpg(proc.pid, signal.SIGINT)
    out += proc.stdout.read()
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    if not serving:
        wall = time.perf_counter() - start
    if code not in (0, 130) or (serving and "Press Ctrl-C" not in out):
        raise SystemExit(f"{' '.join(argv[5:])} failed ({code}): {err.strip()[-500:]}")
    return usage.ru_utime + usage.ru_stime, wall


def install_revision(rev: str, where: Path, env: dict[str, str]) -> Path:
    """A plain install of git revision ``rev`` of this repository (its files only)."""
    tree = where / "tree"
    tree.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    pyproject = tree / "pyproject.toml"  # before this version the wheel lacked rtupoll.app
    text = pyproject.read_text()
    if (tree / "src/rtupoll/app").is_dir() and '"rtupoll.app"' not in text:
        pyproject.write_text(text.replace('"rtupoll.cli",', '"rtupoll.cli", "rtupoll.app",', 1))
    return plain_install(where / "venv", env, tree)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7, help="runs of each command (default 7)")
    ap.add_argument("--before", metavar="REV", help="also time this git revision, interleaved")
    ap.add_argument("--only", action="append", default=[], help="only these commands")
    ap.add_argument("--mbpoll", default=shutil.which("mbpoll"),
                    help="the mbpoll to time beside read (default: the one on PATH)")
    ap.add_argument("--editable", action="store_true",
                    help="also time this checkout's development install (an editable one)")
    args = ap.parse_args()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    with tempfile.TemporaryDirectory() as tmp:
        env["XDG_CACHE_HOME"] = str(Path(tmp) / "cache")  # their own profile cache
        installs = {"after": plain_install(Path(tmp) / "after", env)}
        if args.before:
            installs["before"] = install_revision(args.before, Path(tmp) / "before", env)
        if args.editable:  # its import hook: the before/after of a plain install
            installs["editable"] = Path(sys.executable)
        with simulated_bus(DEVICES, tick=None) as sim:
            measure(args, env, installs, commands(sim.port), sim.port)


def measure(args: argparse.Namespace, env: dict[str, str], installs: dict[str, Path],
            cmds: dict[str, list[str]], port: str) -> None:
    cases: dict[tuple[str, str], tuple[list[str], dict[str, str]]] = {}
    uncached = {**env, "RTUPOLL_NO_PROFILE_CACHE": "1"}
    for which, python in installs.items():
        cases[(which, "python -c pass")] = ([str(python), "-c", "pass"], env)
        cases[(which, "import click, serial")] = ([str(python), "-c", "import click, serial"],
                                                  env)
        for name, argv in cmds.items():
            if not args.only or name in args.only:
                cases[(which, name)] = ([str(python.parent / "rtupoll"), *argv], env)
                if name in UNCACHED:  # does the profile cache pay?
                    cases[(which, f"{name}, no cache")] = (cases[(which, name)][0], uncached)
    if args.mbpoll:  # the C peer reading the same register as ``read``
        cases[("after", "mbpoll (C)")] = ([args.mbpoll, "-m", "rtu", "-b", "9600", "-P", "none",
                                          "-a", "1", "-t", "3", "-r", "30009", "-0", "-c", "1",
                                          "-1", port], env)
    for argv, cenv in cases.values():  # warm-up: .pyc files, the profile cache
        run(argv, cenv)
    got: dict[tuple[str, str], list[tuple[float, float, float]]] = {k: [] for k in cases}
    for _ in range(args.runs):  # interleaved, so the machine's drift hits all alike
        for key, (argv, cenv) in cases.items():
            got[key].append(run(argv, cenv))

    def med(key: tuple[str, str], i: int) -> float:
        return statistics.median(r[i] for r in got[key])

    names = [n for n in dict.fromkeys(name for _, name in cases) if n != "mbpoll (C)"]
    others = [w for w in installs if w != "after"]
    print(f"{args.runs} runs each, medians; CPU = user + system of the process")
    head = f"{'command':24s} {'CPU ms':>7s} {'wall ms':>8s} {'MiB':>6s} {'x pass':>7s}"
    for other in others:
        head += f" {other + ' CPU':>15s} {other + ' MiB':>15s} {'after/' + other:>17s}"
    print(head)
    for name in names:
        a = ("after", name)
        line = (f"{name:24s} {med(a, 0) * 1e3:7.1f} {med(a, 1) * 1e3:8.1f} {med(a, 2):6.1f} "
                f"{med(a, 0) / med(('after', 'python -c pass'), 0):7.2f}")
        for other in others:
            b = (other, name)
            ratios = sorted(x[0] / y[0] for x, y in zip(got[a], got[b], strict=True))
            line += (f" {med(b, 0) * 1e3:15.1f} {med(b, 2):15.1f} "
                     f"{statistics.median(ratios):7.2f} ({ratios[0]:.2f}-{ratios[-1]:.2f})")
        print(line)
    if args.mbpoll and ("after", "read") in got:
        theirs = got[("after", "mbpoll (C)")]
        print(f"mbpoll reading the same register: {med(('after', 'mbpoll (C)'), 0) * 1e3:.1f} ms "
              f"CPU, {med(('after', 'mbpoll (C)'), 1) * 1e3:.1f} ms wall")
        for which in installs:
            ours = got[(which, "read")]
            walls = sorted(x[1] / y[1] for x, y in zip(ours, theirs, strict=True))
            print(f"  read, {which}, wall against mbpoll's, run by run: median "
                  f"x{statistics.median(walls):.2f} ({walls[0]:.2f}-{walls[-1]:.2f})")
    print(f"load average at the end: {os.getloadavg()[0]:.1f}", file=sys.stderr)


if __name__ == "__main__":
    main()
