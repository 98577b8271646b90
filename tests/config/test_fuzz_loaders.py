"""Fuzzing every file loader: random bytes, random YAML, and mutated bundled files.

Whatever the file holds, a loader either accepts it or raises an ``RtupollError`` whose
message starts ``file:line:`` with exit code 2 (8 for a plan row refused as unsafe),
within a bounded time: never another exception (a traceback) and never a hang.
"""

from __future__ import annotations

import re
import signal
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any

import pytest
import yaml
from cli_runner import RTUPOLL, Ran, rtupoll
from forked_cli import rtupoll_run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rtupoll.config.address_plan import load_plan
from rtupoll.config.library import load_profile
from rtupoll.config.site import load_site
from rtupoll.errors import RtupollError
from rtupoll.sim.scenario import build

BUNDLED = Path(__file__).parents[2] / "profiles"
PER_CASE = 5.0  # seconds: a hang or a blow-up fails the case (normal cases take ms)

SITE = """\
profiles: []
buses:
  - name: line1
    port: /dev/ttyUSB0
    baudrate: 9600
    parity: N
    devices:
      - {name: tank, profile: radar-level, address: 4, interval: 2, timeout: 0.5}
      - {name: air, profile: huiwen-aq, address: 3, fields: [co2, pm25], retries: 1}
"""
SCENARIO = """\
seed: 7
baudrate: 9600
turnaround: 0.01
tick: 0
devices:
  - device: net-irnet-pro@1
    variant: 0
    values: {concentration: 12.5, warning: [WARMUP_WARNING], error: NO_ERROR}
  - device: huiwen-aq@3
    write_reply: short
    faults: [crc@10%]
faults: ["1:dead@50-"]
"""
PLAN_YAML = """\
- {profile: radar-level, address: 1, new: 11}
- {profile: huiwen-aq, address: 2, new: 12, check: "co2_failure=NO_FAULT"}
"""
PLAN_CSV = "profile,address,new,check\nradar-level,1,11,\nhuiwen-aq,2,12,co2_failure=NO_FAULT\n"


def _profile(path: Path) -> Any:
    return load_profile(path)


def _scenario(path: Path) -> Any:
    return build(scenario=path)


# kind -> (file name, loader, a good file to mutate, exit codes a refusal may carry)
LOADERS: dict[str, tuple[str, Callable[[Path], Any], str, set[int]]] = {
    "profile": ("huiwen-aq.yaml", _profile, (BUNDLED / "huiwen-aq.yaml").read_text(), {2}),
    "profile-irnet": ("net-irnet-pro.yaml", _profile,
                      (BUNDLED / "net-irnet-pro.yaml").read_text(), {2}),
    "site": ("site.yaml", load_site, SITE, {2}),
    "scenario": ("bus.yaml", _scenario, SCENARIO, {2}),
    "plan": ("plan.yaml", load_plan, PLAN_YAML, {2, 8}),
    "plan-csv": ("plan.csv", load_plan, PLAN_CSV, {2, 8}),
}
KINDS = sorted(LOADERS)

HOSTILE_TOKENS = [
    ".nan", ".inf", "-.inf", '!!float "abc"', '!!int "abc"', '!!bool "maybe"', "!!binary x",
    "!!python/object/apply:os.system [true]", "!!python/name:os.system", "!custom x",
    "*nowhere", "&a", "<<: 5", "<<: [1]", "[", "]", "{", "}", "[[[[[[", "? x", "- - -",
    "'", '"', "\x01", "\x00", "\ufeff", "\udcff", "~", "null", "''", "99999999999999999999999",
    "-1", "0x", "1.0e+999", "0b102", "1_000", "yes", "NO", "@", "%", "`", "|", ">", "#",
    "\t", ": :", "&x [*x]", "!!set {a}", "!!omap [a: 1]", "!!timestamp 2001-01-01",
]


EXTREMES = ["-1", "0", "0.0", "-0.5", "1", "255", "256", "65535", "65536", "1e+9", "1.0e+999",
            "-.inf", ".nan", "99999999999999999999", "0xFFFFFFFF", "4000001", "3601", "86401",
            "0.001", "31", "11", "128"]


@contextmanager
def bounded(seconds: float) -> Iterator[None]:
    """Fail (instead of hanging) when the body takes more than ``seconds`` of CPU time (the
    process's: another process using the machine does not count)."""
    def expired(signum: int, frame: FrameType | None) -> None:
        raise TimeoutError(f"took more than {seconds} CPU seconds")

    previous = signal.signal(signal.SIGPROF, expired)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, previous)


def check(kind: str, data: bytes) -> None:
    """Load ``data`` as ``kind``: accepted, or one ``file:line:`` error of a known code."""
    name, loader, _, codes = LOADERS[kind]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(data)
        t0 = time.process_time()
        try:
            with bounded(PER_CASE):
                loader(path)
        except RtupollError as exc:
            assert exc.exit_code in codes, f"{type(exc).__name__} {exc}"
            assert re.match(rf"{re.escape(str(path))}:[1-9]\d*: .", str(exc)), str(exc)
            assert "\n" not in str(exc).strip() or kind.startswith("plan"), str(exc)
        assert time.process_time() - t0 < PER_CASE


# how many examples: the profile's (tests/conftest.py: short by default, long on demand)
FUZZ = settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.binary(max_size=600))
def test_random_bytes(kind: str, data: bytes) -> None:
    check(kind, data)


YAML_CHARS = st.sampled_from([*"ab01:-[]{},&*!<>|#'\"? \n\t.%@~\\", "\n  ", ": ", "- "])


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(text=st.lists(YAML_CHARS, max_size=200).map("".join))
def test_random_yaml_text(kind: str, text: str) -> None:
    check(kind, text.encode())


SCALARS = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8))
KEYS = st.sampled_from(["id", "fields", "name", "table", "address", "type", "scale", "buses",
                        "devices", "port", "profile", "values", "faults", "limits", "turnaround",
                        "tick", "seed", "new", "check", "enum", "flags", "serial", "x"])
TREES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(KEYS, inner, max_size=5)), max_leaves=20)


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(tree=TREES)
def test_random_yaml_documents(kind: str, tree: Any) -> None:
    check(kind, yaml.safe_dump(tree, allow_unicode=True).encode())


@st.composite
def mutated(draw: st.DrawFn, text: str) -> bytes:
    """A good file, changed in a few places the way a hostile or careless hand would."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.sampled_from(["token", "token", "token", "number", "number", "drop",
                                    "copy", "indent", "truncate"]))
        numbers = list(re.finditer(r"(?<![\w.])-?\d+(\.\d+)?(?![\w.])", lines[i]))
        if how == "number" and numbers:
            m = draw(st.sampled_from(numbers))
            lines[i] = lines[i][:m.start()] + draw(st.sampled_from(EXTREMES)) + lines[i][m.end():]
        elif how in ("token", "number"):
            words = re.split(r"(\s+)", lines[i])
            j = draw(st.integers(0, len(words) - 1))
            words[j] = draw(st.sampled_from(HOSTILE_TOKENS))
            lines[i] = "".join(words)
        elif how == "drop":
            del lines[i]
        elif how == "copy":
            lines.insert(i, lines[i])
        elif how == "indent":
            lines[i] = draw(st.sampled_from(["  ", " ", "\t", ""])) + lines[i].lstrip()
        else:
            lines[i] = lines[i][:draw(st.integers(0, len(lines[i])))]
        if not lines:
            lines = [""]
    data = "\n".join(lines).encode("utf-8", "surrogateescape")
    if draw(st.booleans()):
        k = draw(st.integers(0, len(data)))
        data = data[:k] + draw(st.binary(max_size=4)) + data[k:]
    return data


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.data())
def test_mutated_good_files(kind: str, data: st.DataObject) -> None:
    check(kind, data.draw(mutated(LOADERS[kind][2])))


@pytest.mark.parametrize("kind", KINDS)
def test_the_unmutated_files_load(kind: str) -> None:
    # the mutations start from files that are good: a refusal comes from the mutation
    name, loader, text, _ = LOADERS[kind]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_text(text)
        assert loader(path)


COMMANDS = {  # kind -> the command line that loads such a file ({} is the file)
    "profile": ["profiles", "check", "{}"],
    "site": ["poll", "-c", "{}", "--once", "--format", "json"],
    "scenario": ["simulate", "--scenario", "{}", "--tcp", "127.0.0.1:0"],
    "plan": ["set-address", "-p", "/dev/null", "--plan", "{}", "--dry-run"],
}


@pytest.mark.parametrize("kind", sorted(COMMANDS))
@settings(max_examples=3,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_commands_given_mutated_files(kind: str, data: st.DataObject) -> None:
    """A few whole command runs: one line on stderr with file:line, exit 2; no traceback.
    A mutated file that still loads is run with its port missing (exit 3) or served
    until the timeout stops it (the simulator, which serves until a signal: a process of
    its own; the others run in this process, tests/cli_runner.py)."""
    import subprocess

    content = data.draw(mutated(LOADERS[kind][2]) | st.binary(max_size=300))
    name = LOADERS[kind][0]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(content)
        args = [a.replace("{}", str(path)) for a in COMMANDS[kind]]
        if kind != "scenario":
            proc: subprocess.CompletedProcess[str] | Ran = rtupoll(*args)
        else:
            try:  # a served scenario is stopped after 8 s
                proc = rtupoll_run([RTUPOLL, *args], capture_output=True, text=True,
                                   timeout=8)
            except subprocess.TimeoutExpired:
                return  # a valid scenario is served until stopped
    assert "Traceback" not in proc.stderr, proc.stderr
    if proc.returncode == 2 and str(path) in proc.stderr:
        assert re.search(rf"{re.escape(str(path))}:[1-9]\d*: ", proc.stderr), proc.stderr
    else:  # loaded: then the port is missing, a row refused, or (profiles check) all ok
        assert proc.returncode in (0, 3, 8, 9), proc.stderr
