"""Hostile input, by name: files that used to hang the tool or end in a traceback, and
command lines that were accepted as nonsense (issue 9, parts 2 and 3).

Every loader (profile, site file, scenario, address plan) must answer a bad file with
``file:line: path: message`` and exit 2, in bounded time; the command line must answer
a bad argument, a full disk, a closed stdout or an early signal with one line.
"""

from __future__ import annotations

import json
import math
import os
import re
import resource
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import pytest
from cli_runner import RTUPOLL, Ran, rtupoll
from forked_cli import rtupoll_popen, rtupoll_run

import rtupoll.cli as rtupoll_cli
from rtupoll.config.address_plan import load_plan
from rtupoll.config.library import load_profile
from rtupoll.config.profile_file import MAX_FIELDS
from rtupoll.config.site import load_site
from rtupoll.config.yamlsrc import MAX_BYTES
from rtupoll.errors import Interrupted, ProfileError
from rtupoll.sim.runner import SimulatedBus
from rtupoll.sim.scenario import build

BUNDLED = Path(__file__).parents[2] / "profiles"
FIXTURES = Path(__file__).parents[1] / "fixtures" / "hostile"
# CPU seconds any one hostile file may take (the worst measured: ~1.5 s): CPU time, which
# another process using the machine does not stretch as it stretches the wall clock
LIMIT = 5.0

SITE = """\
buses:
  - name: line1
    port: /dev/ttyUSB0
    baudrate: 9600
    devices:
      - {name: tank, profile: radar-level, address: 4, interval: 2}
"""
SCENARIO = """\
seed: 7
turnaround: 0.01
devices:
  - device: huiwen-aq@3
    values: {co2: 800}
faults: ["3:crc@10%"]
"""
PLAN = """\
- {profile: radar-level, address: 1, new: 11}
"""


def _profile(path: Path) -> Any:
    return load_profile(path)


def _scenario(path: Path) -> Any:
    return build(scenario=path)


LOADERS: dict[str, tuple[str, Callable[[Path], Any]]] = {
    # kind -> (file name, loader); a profile's file name must match its id
    "profile": ("radar-level.yaml", _profile),
    "site": ("site.yaml", load_site),
    "scenario": ("bus.yaml", _scenario),
    "plan": ("plan.yaml", load_plan),
}


def refused(kind: str, data: bytes | str, tmp_path: Path) -> ProfileError:
    """Load ``data`` as ``kind``: it must fail with one line, file:line, exit 2, in bounded
    (CPU) time."""
    name, loader = LOADERS[kind]
    path = tmp_path / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    t0 = time.process_time()
    with pytest.raises(ProfileError) as info:
        loader(path)
    assert time.process_time() - t0 < LIMIT
    err = info.value
    assert err.exit_code == 2
    assert re.match(rf"{re.escape(str(path))}:[1-9]\d*: ", str(err)), str(err)
    assert "\n" not in str(err), str(err)
    return err


def children_cpu() -> float:
    """CPU seconds of this process's finished children (a command's cost, not its wait)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


# -- whole files that are hostile --------------------------------------------------

def billion_laughs() -> str:
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 10):
        lines.append(f"a{i}: &a{i} [{','.join([f'*a{i - 1}'] * 9)}]")
    return "\n".join(lines) + "\n"


WHOLE_FILES: dict[str, tuple[bytes | str, str | None]] = {
    # name -> (content, what the message says: None where the words are the YAML library's,
    # which change between its versions; the behaviour is what refused() checks)
    # the report's 574-byte file: each level merges the one below nine times
    "nested-merge-keys": ((FIXTURES / "nested-merge.yaml").read_text(),
                          "aliases and merge keys are expanded"),
    "billion-laughs": (billion_laughs(), "aliases and merge keys are expanded"),
    "binary-garbage": (bytes(range(256)) * 8, "not UTF-8"),
    "not-utf8": ("id: caf\xe9\n".encode("latin-1"), "not UTF-8 text (byte 0xE9)"),
    "control-character": ("id: radar-level\nvendor: a\x07b\n", "character 0x07"),
    "nul-byte": ("id: radar-level\x00\n", "character 0x00"),
    # rtupoll's depth check says "nested more than 64"; libyaml from PyYAML 6.0.4 on stops
    # at 1,000 levels first, in its own words
    "deep-flow-nesting": ("a: " + "[" * 200_000, None),
    "deep-block-nesting": ("- " * 100_000 + "x\n", "nested more than"),
    "recursive-alias": ("a: &x [1, *x]\n", "contains it"),
    "recursive-merge": ("a: &x {b: 1, c: {<<: *x}}\n", "contains it"),
    "empty": ("", "empty"),
    "syntax": ("a: [1, 2\nb: 3\n", "YAML syntax"),
}


@pytest.mark.parametrize("kind", sorted(LOADERS))
@pytest.mark.parametrize("case", sorted(WHOLE_FILES))
def test_a_hostile_file_is_one_line_with_file_and_line(kind: str, case: str,
                                                       tmp_path: Path) -> None:
    content, says = WHOLE_FILES[case]
    err = refused(kind, content, tmp_path)
    assert says is None or says in str(err)
    if isinstance(content, str) and content.count("\n") <= 1:
        assert err.line == 1  # a file of one line: that line


@pytest.mark.parametrize("kind", sorted(LOADERS))
def test_a_ten_megabyte_file_is_refused_unread(kind: str, tmp_path: Path) -> None:
    # the report's file: 131,072 fields, 10 MB; refused by size before parsing
    field = "  - {name: f, table: input, address: 1, type: u16}\n"
    data = "id: radar-level\nfields:\n" + field * (10_000_000 // len(field))
    err = refused(kind, data, tmp_path)
    assert f"larger than {MAX_BYTES >> 10} KiB" in str(err)
    assert err.line == 1


# -- values in otherwise good files ----------------------------------------------

def _radar(**limits: str) -> str:
    text = (BUNDLED / "radar-level.yaml").read_text()
    for key, value in limits.items():
        text, n = re.subn(rf"(?m)^  {key}: .*$", f"  {key}: {value}", text)
        assert n == 1, key
    return text


PROFILE_VALUES = {
    # name -> (limits key, value, what the message says)
    "python-tag": ("timeout", '!!python/object/apply:os.system "true"',
                   "unsupported tag !!python/object/apply:os.system"),
    "python-name": ("timeout", "!!python/name:os.system x", "unsupported tag"),
    "float-abc": ("timeout", '!!float "abc"', "'abc' is not a valid !!float"),
    "int-abc": ("retries", '!!int "abc"', "'abc' is not a valid !!int"),
    "bool-maybe": ("retries", '!!bool "maybe"', "'maybe' is not a valid !!bool"),
    "turnaround-nan": ("turnaround", ".nan", "expected a finite number, got .nan"),
    "turnaround-inf": ("turnaround", ".inf", "expected a finite number"),
    "timeout-nan": ("timeout", ".NaN", "expected a finite number"),
    "merge-scalar": ("timeout", "0.3\n  <<: 5", "a merge key (<<) takes a mapping"),
    "huge-int": ("retries", "9" * 5000, "is not a valid !!int"),
    "huge-float": ("timeout", "1.0e+999", "expected a finite number"),
}


@pytest.mark.parametrize("case", sorted(PROFILE_VALUES))
def test_a_profile_value_that_used_to_crash_is_a_line(case: str, tmp_path: Path) -> None:
    key, value, says = PROFILE_VALUES[case]
    err = refused("profile", _radar(**{key: value}), tmp_path)
    assert says in str(err)
    assert err.path.startswith("limits") or case == "merge-scalar", str(err)


def test_a_python_tag_on_text_is_refused_too(tmp_path: Path) -> None:
    text = (BUNDLED / "radar-level.yaml").read_text().replace(
        "model: 60 GHz", "model: !!python/name:os.system 60 GHz")
    err = refused("profile", text, tmp_path)
    assert "model: unsupported tag !!python/name:os.system" in str(err)


@pytest.mark.parametrize("where,value", [
    ("scale", ".nan"), ("scale", ".inf"), ("scale", "-.inf"), ("offset", ".nan"),
    ("values", "[.nan]"), ("values", "[1, .inf]"), ("range", "[0, .nan]")])
def test_nan_and_infinity_are_refused_where_a_number_is_meant(where: str, value: str,
                                                            tmp_path: Path) -> None:
    text = (BUNDLED / "radar-level.yaml").read_text().replace(
        "{name: level_mm, table: holding, address: 0x0003, type: u16, unit: mm,",
        f"{{name: level_mm, table: holding, address: 0x0003, type: u16, unit: mm, "
        f"{where}: {value},")
    err = refused("profile", text, tmp_path)
    assert "expected a finite number" in str(err)
    assert ".level_mm" not in err.path and err.path.startswith("fields[3]")


@pytest.mark.parametrize("key,value", [("interval", ".nan"), ("interval", ".inf"),
                                       ("timeout", ".nan")])
def test_a_site_number_must_be_finite(key: str, value: str, tmp_path: Path) -> None:
    err = refused("site", SITE.replace("interval: 2", f"interval: 2, {key}: {value}")
                  .replace("interval: 2, interval", "interval"), tmp_path)
    assert "finite number" in str(err)


@pytest.mark.parametrize("text,says", [
    ("turnaround: .nan", "finite number"),
    ("turnaround: 50", "outside 0..10 s"),
    ("turnaround: !!float abc", "not a valid !!float"),
    ("seed: !!int abc", "not a valid !!int"),
    ("tick: .nan", "finite number"),
    ("tick: -1", "outside 0..3600"),
])
def test_a_scenario_number_must_make_sense(text: str, says: str, tmp_path: Path) -> None:
    key = text.split(":")[0]
    base = SCENARIO if key in ("seed", "turnaround") else SCENARIO + "tick: 1\n"
    err = refused("scenario", re.sub(rf"(?m)^{key}: .*$", text, base), tmp_path)
    assert says in str(err)


def test_a_scenario_nan_pin_on_a_scaled_integer_is_a_line(tmp_path: Path) -> None:
    err = refused("scenario", SCENARIO.replace("{co2: 800}", "{temperature: .nan}"), tmp_path)
    assert "temperature" in str(err) and "nan" in str(err)


def test_a_scenario_may_pin_nan_on_a_float_register(tmp_path: Path) -> None:
    # a float register holding NaN is what a device may really send: the simulator can
    (tmp_path / "bus.yaml").write_text(
        "devices:\n  - device: net-irnet-pro@1\n    values: {concentration: .nan}\n")
    config = build(scenario=tmp_path / "bus.yaml")
    pinned = config.devices[0].pins["concentration"]
    assert isinstance(pinned, float) and math.isnan(pinned)


def test_a_fault_with_nothing_after_the_at_sign_is_refused(tmp_path: Path) -> None:
    err = refused("scenario", SCENARIO.replace('"3:crc@10%"', '"3:dead@"'), tmp_path)
    assert "nothing after '@'" in str(err)


# -- address plans (CSV) -----------------------------------------------------------

@pytest.mark.parametrize("data,says", [
    ("profile,address,new\nradar-level,1,caf\xe9\n".encode("latin-1"), "not UTF-8"),
    ("profile,address,new\nradar-level,1,\x0011\n", "control character"),
    (b"", "empty"),
    ("profile,address,new\n" + "x" * 200_000 + ",1,2\n", "CSV: field larger"),
])
def test_a_hostile_csv_plan_is_a_line(data: bytes | str, says: str, tmp_path: Path) -> None:
    path = tmp_path / "plan.csv"
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    with pytest.raises(ProfileError) as info:
        load_plan(path)
    assert re.match(rf"{re.escape(str(path))}:[1-9]\d*: ", str(info.value)), str(info.value)
    assert says in str(info.value)


# -- the overlap check: n log n, and a cap ------------------------------------------

def _fields_profile(n: int, *, overlap: bool = False) -> str:
    head = (BUNDLED / "radar-level.yaml").read_text().split("\nfields:\n")[0]
    head = re.sub(r"(?ms)^identify:.*?(?=^set_address:)", "", head)
    head = re.sub(r"(?ms)^set_address:.*\Z", "", head)
    lines = [f"  - {{name: f{i}, table: holding, address: {i}, type: u16}}" for i in range(n)]
    if overlap:
        lines.append(f"  - {{name: late, table: holding, address: {n // 2}, type: u32}}")
    return head + "\nfields:\n" + "\n".join(lines) + "\n"


def test_four_thousand_fields_are_checked_quickly(tmp_path: Path) -> None:
    path = tmp_path / "radar-level.yaml"
    path.write_text(_fields_profile(4000))
    t0 = time.process_time()
    profile = load_profile(path)
    assert len(profile.fields) == 4000
    assert time.process_time() - t0 < LIMIT  # quadratic took ~1.6 s for 4,000, 6.5 s for 8,000


def test_an_overlap_is_reported_at_the_later_field(tmp_path: Path) -> None:
    err = refused("profile", _fields_profile(300, overlap=True), tmp_path)
    assert "late overlaps f150 (line" in str(err)
    assert err.path == "fields[300].address"


def test_a_profile_holds_at_most_max_fields(tmp_path: Path) -> None:
    err = refused("profile", _fields_profile(MAX_FIELDS + 1), tmp_path)
    assert f"at most {MAX_FIELDS}" in str(err)


# -- site files: a profile file is found from the site file's folder ----------------

def test_a_site_profile_file_is_resolved_from_the_site_folder(tmp_path: Path) -> None:
    site_dir = tmp_path / "site"
    (site_dir / "mine").mkdir(parents=True)
    (site_dir / "mine" / "radar-level.yaml").write_text(
        (BUNDLED / "radar-level.yaml").read_text())
    (site_dir / "site.yaml").write_text(SITE.replace("profile: radar-level",
                                                     "profile: mine/radar-level.yaml"))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    old = os.getcwd()
    os.chdir(elsewhere)
    try:
        site = load_site(Path("../site/site.yaml"))
        used = Path(site.buses[0].devices[0].profile.path).resolve()
    finally:
        os.chdir(old)
    assert used == (site_dir / "mine" / "radar-level.yaml").resolve()


def test_a_missing_site_profile_file_has_a_line(tmp_path: Path) -> None:
    err = refused("site", SITE.replace("profile: radar-level", "profile: nope.yaml"), tmp_path)
    assert err.line == 6 and "no profile file" in str(err)
    assert str(tmp_path / "nope.yaml") in str(err)


# -- NaN and infinities in JSON and CSV --------------------------------------------


def test_read_json_of_a_nan_register_is_strict_json(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("net-irnet-pro@1", tick=None, sets=["net-irnet-pro@1.concentration=nan"])
    result = rtupoll("read", "-p", bus.port, "--format", "json", "net-irnet-pro@1",
                     "concentration")
    assert result.returncode == 0, result.stderr
    rec = json.loads(result.stdout, parse_constant=lambda c: pytest.fail(f"bare {c}"))
    assert rec["value"] is None and rec["text"] == "NaN"
    csv = rtupoll("read", "-p", bus.port, "--format", "csv", "net-irnet-pro@1", "concentration")
    row = csv.stdout.splitlines()[1]
    assert ",concentration,,ppm," in row and row.endswith(",NaN")  # value empty, text NaN


def test_poll_json_of_a_nan_register_is_strict_json(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("net-irnet-pro@1", tick=None, sets=["net-irnet-pro@1.concentration=-inf"])
    result = rtupoll("poll", "-p", bus.port, "-b", "4800", "--once", "--format", "json",
                     "net-irnet-pro@1")
    assert result.returncode == 0, result.stderr
    recs = [json.loads(line, parse_constant=lambda c: pytest.fail(f"bare {c}"))
            for line in result.stdout.splitlines()]
    conc = next(r for r in recs if r["field"] == "concentration")
    assert (conc["value"], conc["text"], conc["status"]) == (None, "-inf", "ok")


# -- the command line ----------------------------------------------------------------

def one_line(proc: subprocess.CompletedProcess[str] | Ran) -> str:
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


@pytest.mark.parametrize("args,says", [
    (["read", "-p", "/dev/null", "-b", "99999999999", "huiwen-aq@3"],
     "99999999999 is not in the range 300<=x<=4000000"),
    (["read", "-p", "/dev/null", "-b", "0", "huiwen-aq@3"], "0 is not in the range 300<="),
    (["write", "-p", "/dev/null", "-b", "0", "radar-level@1", "slave_address=2"],
     "'--baudrate' / '-b': 0 is not in the range"),
    (["set-address", "-p", "/dev/null", "-b", "0", "radar-level@1", "2"],
     "'--baudrate' / '-b': 0 is not in the range"),
    (["poll", "-p", "/dev/null", "--interval", "nan", "huiwen-aq@3"], "not a number of seconds"),
    (["poll", "-p", "/dev/null", "--timeout", "nan", "huiwen-aq@3"], "not a number of seconds"),
    (["read", "-p", "/dev/null", "--timeout", "nan", "huiwen-aq@3", "co2"],
     "not a number of seconds"),
    (["simulate", "--tick", "nan"], "not a number of seconds"),
    (["simulate", "--turnaround", "nan"], "not a number of seconds"),
    (["simulate", "--tcp", "127.0.0.1:99999"], "PORT 0..65535"),
    (["simulate", "--fault", "3:dead@"], "nothing after '@'"),
])
def test_nonsense_on_the_command_line_is_refused(args: list[str], says: str) -> None:
    proc = rtupoll(*args)
    assert proc.returncode == 2, proc.stderr
    assert says in one_line(proc)


@pytest.mark.parametrize("kind,args", [
    ("profile", ["profiles", "check", "{}"]),
    ("profile", ["decode", "--profile", "{}", "01", "04", "00", "06", "00", "02", "91", "CA"]),
    ("site", ["poll", "-c", "{}", "--once"]),
    ("scenario", ["simulate", "--scenario", "{}"]),
    ("plan", ["set-address", "-p", "/dev/null", "--plan", "{}", "--dry-run"]),
])
@pytest.mark.parametrize("case", ["nested-merge-keys", "binary-garbage", "deep-flow-nesting"])
def test_every_command_that_loads_a_file_gives_its_line(kind: str, args: list[str], case: str,
                                                        tmp_path: Path) -> None:
    path = tmp_path / LOADERS[kind][0]
    content = WHOLE_FILES[case][0]
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    proc = rtupoll(*[a.replace("{}", str(path)) for a in args])  # in this process
    assert proc.cpu < LIMIT
    assert_gives_its_line(proc, path)


def assert_gives_its_line(proc: subprocess.CompletedProcess[str] | Ran, path: Path) -> None:
    assert proc.returncode == 2, proc.stderr
    assert re.search(rf"{re.escape(str(path))}:[1-9]\d*: ", proc.stderr), proc.stderr
    assert "Traceback" not in proc.stderr
    assert sum(str(path) in line for line in proc.stderr.splitlines()) == 1, proc.stderr


@pytest.mark.parametrize("case", ["binary-garbage", "deep-flow-nesting"])
def test_the_installed_command_gives_a_hostile_files_line(case: str, tmp_path: Path) -> None:
    """The same, as a process of its own (the rest run in this one: tests/cli_runner.py)."""
    path = tmp_path / LOADERS["site"][0]
    content = WHOLE_FILES[case][0]
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    cpu = children_cpu()
    proc = subprocess.run([RTUPOLL, "poll", "-c", str(path), "--once"], capture_output=True,
                          text=True, timeout=60)
    assert children_cpu() - cpu < LIMIT + 5  # the whole command, start-up included
    assert_gives_its_line(proc, path)


def test_a_full_disk_is_one_line(tmp_path: Path) -> None:
    with open("/dev/full", "w") as full:
        proc = rtupoll_run([RTUPOLL, "profiles", "list"], stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=30)
    assert proc.returncode == 2
    assert one_line(proc) == "rtupoll: cannot write the output: No space left on device"


def test_a_closed_stdout_is_one_line() -> None:
    proc = subprocess.run(f"exec {RTUPOLL} profiles list >&-", shell=True,
                          stderr=subprocess.PIPE, text=True, timeout=30)
    assert proc.returncode == 2
    assert one_line(proc) == "rtupoll: cannot write the output: Bad file descriptor"


def test_json_to_a_full_disk_after_a_read_is_one_line(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    with open("/dev/full", "w") as full:
        proc = rtupoll_run([RTUPOLL, "read", "-p", bus.port, "--format", "json",
                               "huiwen-aq@3"], stdout=full, stderr=subprocess.PIPE, text=True,
                              timeout=30)
    assert proc.returncode == 2
    assert "No space left on device" in one_line(proc)


def package_roots() -> dict[str, str]:
    """The folders of the installed packages whose frames the early-signal check counts."""
    return {"rtupoll": str(Path(rtupoll_cli.__file__).parents[1]),
            "click": os.path.dirname(click.__file__ or "")}


def after_our_handler(err: str, roots: dict[str, str]) -> list[str]:
    """Traceback frames in click or rtupoll (files inside ``roots``, the packages' folders)
    from after rtupoll's early signal handler is in place (the lines of
    ``rtupoll/cli/__init__.py`` before it, and the package's ``__init__``, run before any
    handler can: like Python's own start-up). A frame is placed by where its file is, not by
    a folder name in its path: a checkout or a venv may itself be in a folder ``rtupoll``."""
    source = Path(rtupoll_cli.__file__).read_text()
    handler = next(i for i, line in enumerate(source.splitlines(), 1)
                   if "_signal.signal(" in line)
    frames = []
    for file, n in re.findall(r'^ *File "([^"]+)", line (\d+)', err, re.MULTILINE):
        for name, root in roots.items():
            if file.startswith(root + os.sep):
                frames.append((f"{name}/{file[len(root) + 1:]}", int(n)))
    return [f"{f}:{n}" for f, n in frames if f != "rtupoll/__init__.py"
            and not (f == "rtupoll/cli/__init__.py" and n <= handler)]


def test_frames_are_placed_by_the_package_folder_not_by_a_folder_name() -> None:
    """A clone is a folder named rtupoll: its venv's click and its src/rtupoll both have
    ``rtupoll/`` in their paths (a regex on the folder name read them as the package's)."""
    clone = "/home/u/rtupoll"
    roots = {"rtupoll": f"{clone}/src/rtupoll",
             "click": f"{clone}/.venv/lib/python3.11/site-packages/click"}
    err = (f'Traceback (most recent call last):\n'
           f'  File "{clone}/.venv/bin/rtupoll", line 5, in <module>\n'
           f'  File "{clone}/src/rtupoll/__init__.py", line 3, in <module>\n'
           f'  File "{clone}/src/rtupoll/cli/__init__.py", line 2, in <module>\n'
           f'  File "<frozen importlib._bootstrap>", line 1360, in _find_and_load\n'
           f'  File "{clone}/.venv/lib/python3.11/site-packages/rtupoll_x/a.py", line 1\n'
           f'KeyboardInterrupt\n')
    assert after_our_handler(err, roots) == []  # before the handler: Python's start-up
    late = err.replace("cli/__init__.py\", line 2", "cli/__init__.py\", line 999") + (
        f'  File "{clone}/.venv/lib/python3.11/site-packages/click/core.py", line 7, in x\n')
    assert after_our_handler(late, roots) == ["rtupoll/cli/__init__.py:999", "click/core.py:7"]


def venv_in_a_folder_named_rtupoll(tmp_path: Path) -> tuple[str, dict[str, str]]:
    """A virtualenv inside a folder ``rtupoll`` (as ``git clone`` makes), running this
    checkout's rtupoll and this venv's click through symlinks, so every frame's path has a
    folder ``rtupoll`` in it: the console script, and the package roots as seen from it."""
    clone = tmp_path / "rtupoll"
    clone.mkdir()
    (clone / "src").symlink_to(Path(rtupoll_cli.__file__).parents[2])
    (clone / "deps").symlink_to(Path(click.__file__).parents[1])
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(clone / ".venv")],
                   check=True, timeout=60)
    python = clone / ".venv" / "bin" / "python"
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                          check=True, capture_output=True, text=True, timeout=30).stdout.strip()
    Path(site, "clone.pth").write_text(f"{clone / 'src'}\n{clone / 'deps'}\n")
    script = clone / ".venv" / "bin" / "rtupoll"
    script.write_text(f"#!{python}\nimport sys\nfrom rtupoll.cli import main\n"
                      f"sys.exit(main())\n")
    script.chmod(0o755)
    return str(script), {"rtupoll": str(clone / "src" / "rtupoll"),
                         "click": str(clone / "deps" / "click")}


def reading(pid: int) -> None:
    """Wait until process ``pid`` is blocked reading a pipe (a guard of 60 s against a
    hang, not a timing claim)."""
    deadline = time.monotonic() + 60
    while "pipe" not in Path(f"/proc/{pid}/wchan").read_text():
        assert time.monotonic() < deadline, "the command never waited for its input"
        time.sleep(0.02)


@pytest.mark.parametrize("sig,where", [(signal.SIGINT, "here"), (signal.SIGTERM, "here"),
                                       (signal.SIGINT, "a folder named rtupoll")])
def test_an_early_signal_never_shows_our_traceback(sig: signal.Signals, where: str,
                                                   tmp_path: Path) -> None:
    """Signals while Python starts and imports: from the first line of rtupoll's code on,
    one line and exit 130. (The interpreter's own start-up, before any of it runs, can
    still print its KeyboardInterrupt; that is not in the package's hands.) Also from a
    venv in a folder named rtupoll, which is what ``git clone`` makes."""
    if where == "here":
        command, roots = RTUPOLL, package_roots()
    else:
        command, roots = venv_in_a_folder_named_rtupoll(tmp_path)
        version = subprocess.run([command, "--version"], capture_output=True, text=True,
                                 timeout=30)
        assert version.returncode == 0, version.stderr
    codes = []
    # every moment of the start-up for Ctrl-C here; for SIGTERM (the same handler) and
    # for the other folder (the same moments, another path) every other one
    delays = [0.0, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1, 0.15, 0.2, 0.3]
    if (sig, where) != (signal.SIGINT, "here"):
        delays = delays[::2]
    for delay in (*delays, None):
        # 'decode -' reads stdin, which stays open: it waits until the signal
        proc = subprocess.Popen([command, "decode", "-"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if delay is None:  # the last one once the command waits for its input, however
            reading(proc.pid)  # long start-up takes on a loaded machine
        else:
            time.sleep(delay)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
        assert not after_our_handler(err, roots), err
        if proc.returncode == 130:
            assert err.strip().splitlines()[-1] == "rtupoll: interrupted", err
        codes.append(proc.returncode)
    # once it runs: one line, exit 130, also for SIGTERM; before that the signal may
    # land in Python's own start-up (how early depends on the machine's load), which
    # ends the process its own way, but never with a traceback through rtupoll's code
    assert codes[-1] == 130, codes


def test_the_early_handler_exits_as_interrupted_does() -> None:
    """The early handler runs before errors.py is imported, so it has its own copy."""
    assert Interrupted.exit_code == rtupoll_cli.EARLY_EXIT


def test_an_error_raised_while_handling_ctrl_c_counts_as_interrupted() -> None:
    """Ctrl-C inside an import can come out of importlib as its own KeyError, with the
    KeyboardInterrupt as its context (CI saw it once): that is an interruption, exit 130."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise KeyError(139941734919040) from None
    except KeyError as exc:
        assert exc.__context__ is not None
        assert rtupoll_cli._from_interrupt(exc)
    assert not rtupoll_cli._from_interrupt(KeyError(1))
    chained = ValueError("x")
    chained.__context__ = chained  # a cycle ends the walk
    assert not rtupoll_cli._from_interrupt(chained)


def test_an_interrupted_plan_reports_every_row(sim: Callable[..., SimulatedBus],
                                               tmp_path: Path) -> None:
    """SIGINT while row 1's write is on the wire: row 1 written, unverified; 2 and 3 not run."""
    bus = sim("radar-level@1", "radar-level@2", "radar-level@3", tick=None,
              faults=["1:slow=1.2@2-"])  # the write (request 2 to unit 1) is answered late
    plan = tmp_path / "plan.csv"
    plan.write_text("profile,address,new\nradar-level,1,11\nradar-level,2,12\n"
                    "radar-level,3,13\n")
    proc = rtupoll_popen([RTUPOLL, "set-address", "-p", bus.port, "-b", "9600",
                             "--timeout", "1.5", "--retries", "0", "--yes", "--format", "json",
                             "--plan", str(plan)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 20
    while not any(w.direction == "in" and len(w.data) >= 2 and w.data[:2] == b"\x01\x06"
                  for w in bus.wire):
        assert time.monotonic() < deadline and proc.poll() is None, "no write was sent"
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert [(r["row"], r["status"], r["exit_code"]) for r in rows] == [
        (1, "written, unverified", 130), (2, "not run", None), (3, "not run", None)]
    assert "may be at 11 or still at 1" in rows[0]["detail"]
    assert "Traceback" not in err and err.strip().endswith("rtupoll: interrupted")


def test_a_raw_write_to_the_address_register_says_where_the_device_went(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    proc = rtupoll("write", "-p", bus.port, "--raw", "--yes", "--format", "json",
                   "huiwen-aq@3", "holding:0x9C41=7")
    assert proc.returncode == 0, proc.stderr
    assert bus.addresses() == {"huiwen-aq@3": 7}
    assert "huiwen-aq's address register (slave_address): writing 7 there moves the device " \
           "to address 7; it answers there now" in one_line(proc)
    assert json.loads(proc.stdout)["value"] == 7


def test_a_raw_write_of_an_unreachable_address_is_refused(
        sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@3", tick=None)
    proc = rtupoll("write", "-p", bus.port, "--raw", "--yes", "huiwen-aq@3", "holding:0x9C41=0")
    assert proc.returncode == 8
    assert "outside its range 1..247" in one_line(proc)
    assert bus.addresses() == {"huiwen-aq@3": 3}
