"""Every shell example in README.md and docs/*.md runs, as printed, against the simulator.

How to write examples so this test runs them (docs/architecture.md, "Documentation
examples", says the same):

- Examples are the lines of ```sh, ```bash, ```shell and ```console blocks that start
  with ``rtupoll``, ``scripts/``, ``mbpoll`` or ``.venv/bin/`` (in ``console`` blocks:
  lines starting with ``$ ``; the rest is output). A line ending in ``\\`` continues.
  Other lines (comments, ``export``) are not run.
- They run against the default demo, whatever the port is called in the text:
  ``/dev/ttyUSB0`` is its line 1 (9600 8N1: net-irnet-pro@1, radar-level@2, huiwen-aq@3,
  banner-ez-array@5) and ``/dev/ttyUSB1`` its line 2 (115200 8N1: co2meter-an117@4).
  So write examples with those devices and speeds, or mark them.
- A trailing comment with ``needs: WHAT`` (``# the frames it would send; needs:
  hardware``) marks an example that cannot run here (hardware, broker, terminal,
  minutes ...): it is skipped and listed. ``<!-- needs: WHAT -->`` on the lines right
  before a block marks the whole block.
- The expected exit status is 0, or ``exit: N`` in the trailing comment
  (``# a dead device; exit: 9``).
- ``<!-- file: NAME -->`` right before a block (YAML, CSV ...) saves it as NAME in the
  examples' working directory, ports replaced as above, so ``-c NAME`` works.
- ``<!-- example: script -->`` runs the whole block as one bash script (exit 0 expected;
  ``$RTUPOLL_PORT`` is line 1).
- Each block runs against a fresh demo, so a block that changes addresses affects only
  itself. Commands that run until stopped (``poll`` without ``--once``, ``simulate``,
  ``scripts/poll``) get SIGINT as soon as they have shown what they show (``shown``: a
  live table with a scan's readings, a record, the simulator's banner to "Press Ctrl-C
  to stop."), as a person would press Ctrl-C, and must then exit with their status.
- An example printed again elsewhere (README and a guide showing the same command) runs
  where it is printed first, when it is self-contained (``_repeat_key``: no demo port,
  no file of the working directory but the documents' own, no shell syntax): it does
  the same there and leaves nothing the examples after it see. It is listed as skipped.
- A plain ``rtupoll ARGS`` line (no shell syntax) runs forked from a server that has
  imported rtupoll once (``forks``, tests/forked_cli.py): the same command in a process
  and session of its own, as a shell would start it (a Ctrl-C stops it as it stops a
  fresh one), without Python's and rtupoll's start-up each time;
  ``test_a_forked_command_is_a_fresh_one`` compares the two. The other lines run with bash.
- ```text blocks (synopses, transcripts that need a person) are not run. Examples that
  name a fixed network port (``127.0.0.1:9464``, also in a ``file:`` block they use)
  never run at the same time as each other.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import fcntl
import functools
import hashlib
import os
import pty
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import pytest
from forked_cli import Forked, ForkServer, shared_server

from rtupoll.sim.runner import SimulatedLines, simulated_lines
from rtupoll.sim.scenario import build

ROOT = Path(__file__).parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELLS = {"sh", "bash", "shell", "console"}
COMMANDS = ("rtupoll", "scripts/", "mbpoll", ".venv/bin/")
RUN_FOR = 1.0  # how long one that runs until stopped runs when it writes only to stderr
SHOWN_BY = 60.0  # a command that runs until stopped and has shown nothing by then: stuck
CAP = 120.0  # a command that should end and has not by then is stuck (a failure)
PORTS = {"/dev/ttyUSB0": "ttyUSB0", "/dev/ttyUSB1": "ttyUSB1"}
COMMENT = re.compile(r"^\s*<!--\s*(.*?)\s*-->\s*$")


@dataclasses.dataclass(frozen=True)
class Block:
    doc: Path
    line: int  # of the opening fence
    lang: str
    text: str
    notes: tuple[str, ...]  # HTML comments right before the fence

    def note(self, key: str) -> str | None:
        for n in self.notes:
            m = re.search(rf"\b{key}:\s*([^;]+?)\s*(?:;|$)", n)
            if m:
                return m.group(1)
        return None


@dataclasses.dataclass(frozen=True)
class Example:
    block: Block
    line: int
    command: str
    needs: str | None = None
    exit: int = 0
    script: bool = False

    @property
    def where(self) -> str:
        return f"{self.block.doc.relative_to(ROOT)}:{self.line}"

    @property
    def runs_until_stopped(self) -> bool:
        c = self.command
        if self.script or "--once" in c or "--help" in c:
            return False
        return bool(re.search(r"(^|\s|/)(rtupoll\s+simulate|rtupoll\s+poll|scripts/poll)\b", c))


def blocks(doc: Path) -> list[Block]:
    out: list[Block] = []
    lines = doc.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^(\s*)```\s*([\w+-]*)", lines[i])
        if not m:
            i += 1
            continue
        notes: list[str] = []
        j = i - 1
        while j >= 0 and COMMENT.match(lines[j]):
            notes.insert(0, COMMENT.match(lines[j]).group(1))  # type: ignore[union-attr]
            j -= 1
        end = i + 1
        while end < len(lines) and not re.match(r"^\s*```\s*$", lines[end]):
            end += 1
        indent = len(m.group(1))
        body = "\n".join(x[indent:] for x in lines[i + 1:end])
        out.append(Block(doc, i + 1, m.group(2).lower(), body, tuple(notes)))
        i = end + 1
    return out


def split_comment(line: str) -> tuple[str, str]:
    """``command  # comment`` -> (command, comment), minding quotes."""
    quote = ""
    for k, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (k == 0 or line[k - 1].isspace()):
            return line[:k].rstrip(), line[k + 1:].strip()
    return line.rstrip(), ""


def examples(block: Block) -> list[Example]:
    if block.lang not in SHELLS:
        return []
    needs = block.note("needs")
    if block.note("example") == "script":
        return [Example(block, block.line + 1, block.text, needs, script=True)]
    out: list[Example] = []
    pending, start = "", 0
    for n, raw in enumerate(block.text.splitlines(), start=block.line + 1):
        line = raw.strip()
        if block.lang == "console":
            if pending:
                line = line.removeprefix("> ")
            elif line.startswith("$ "):
                line = line[2:]
            else:
                continue
        if not pending:
            start = n
        if line.endswith("\\"):
            pending += line[:-1].rstrip() + " "
            continue
        text, comment = split_comment(pending + line)
        pending = ""
        if not text.startswith(COMMANDS):
            continue
        need = re.search(r"needs:\s*([^;]+?)\s*(?:;|$)", comment)
        code = re.search(r"exit:\s*(\d+)", comment)
        out.append(Example(block, start, text, need.group(1) if need else needs,
                           int(code.group(1)) if code else 0))
    return out


def files(doc_blocks: list[Block]) -> dict[str, str]:
    return {name: b.text + "\n" for b in doc_blocks if (name := b.note("file"))}


def ported(text: str, where: Path) -> str:
    for dev, name in PORTS.items():
        text = text.replace(dev, str(where / name))
    return re.sub(r"(?<![\w/.])(\.venv/bin/|scripts/)", lambda m: f"{ROOT}/{m.group(1)}", text)


def setup_is_current() -> bool:
    """``scripts/poll`` would reinstall the shared .venv when pyproject.toml changed."""
    stamp = ROOT / ".venv" / ".rtupoll-setup"
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()[:16]
    return stamp.exists() and digest in stamp.read_text()


NETWORK = threading.Lock()  # examples that bind a fixed port take turns (threads) ...
NETWORK_FILE = Path(tempfile.gettempdir()) / "rtupoll-docs-examples.lock"  # (processes)
FIXED_PORT = re.compile(r"(\d{1,3}(\.\d{1,3}){3}|localhost|\[::1?\]):[1-9]\d{1,4}\b")


def run(ex: Example, where: Path, docfiles: dict[str, str], forks: ForkServer | None = None
        ) -> str | None:
    """Run one example; None if it did what the document says, else why not."""
    uses = ex.command + "".join(t for n, t in docfiles.items() if n in ex.command)
    if FIXED_PORT.search(uses):
        with NETWORK, NETWORK_FILE.open("a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # also across pytest-xdist workers
            return _run(ex, where, forks)
    return _run(ex, where, forks)


def examples_env() -> dict[str, str]:
    """The environment the examples run in: a reader's, with this venv's commands."""
    env = {**os.environ, "COLUMNS": "100", "LINES": "50", "XDG_CACHE_HOME": _examples_cache(),
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    for name in ("RTUPOLL_PROFILES", "RTUPOLL_PORT", "RTUPOLL_TIMEOUT", "RTUPOLL_RETRIES",
                 "PYTHONDONTWRITEBYTECODE"):  # (Python compiles rtupoll once, not each time)
        env.pop(name, None)
    return env


@functools.cache
def _examples_cache() -> str:
    """The examples' compiled-profile cache: this test process's copy of the run's
    (tests/conftest.py), which the other test processes share, so that an example that
    clears its cache (docs/profiles.md) clears only this one."""
    where = tempfile.mkdtemp(prefix="rtupoll-examples-cache-")
    atexit.register(shutil.rmtree, where, ignore_errors=True)
    # not a file another process is writing (``.NAME.tmp``, renamed into place when
    # complete: seen gone half-way through the copy)
    shutil.copytree(os.environ["XDG_CACHE_HOME"], where, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns(".*.tmp"))
    return where


SHELL_SYNTAX = re.compile(r"[|&;<>$`()*?\[\]{}~\\]")  # what needs bash to mean what it says


def forkable(command: str) -> list[str] | None:
    """``rtupoll ARGS`` with nothing for a shell to do but split the words: its argv for
    the fork server (the console script's path first, as a shell would start it)."""
    if SHELL_SYNTAX.search(command):
        return None
    argv = shlex.split(command)
    if not argv or argv[0] != "rtupoll":
        return None
    return [str(Path(sys.executable).parent / "rtupoll"), *argv[1:]]


FORKED_CPU = [0.0]  # CPU seconds of the forked commands so far (they are the server's children)


def _run(ex: Example, where: Path, forks: ForkServer | None) -> str | None:
    env = examples_env()
    if ex.script:
        env["RTUPOLL_PORT"] = str(where / "ttyUSB0")
    command = ported(ex.command, where)
    argv = None if forks is None or ex.script else forkable(command)
    # a command that runs until stopped writes to a terminal, as for a person: so a live
    # table draws at once, and "it has started" can be seen
    terminal = pty.openpty() if ex.runs_until_stopped else None
    seen: list[bytes] = []
    arrived = threading.Event()  # set by the reader when the terminal shows more
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc: subprocess.Popen[str] | Forked
        if argv is not None and forks is not None:
            with open(os.devnull, "rb") as nothing:
                proc = forks.spawn(argv, where, env, nothing.fileno(),
                                   terminal[1] if terminal else out.fileno(), err.fileno())
        else:
            proc = subprocess.Popen(["bash", "-c", command], cwd=where, env=env,
                                    stdin=subprocess.DEVNULL,
                                    stdout=terminal[1] if terminal else out, stderr=err,
                                    text=True, start_new_session=True)
        if terminal is not None:
            os.close(terminal[1])
            reader = threading.Thread(target=_drain, args=(terminal[0], seen, arrived),
                                      daemon=True)
            reader.start()
        why = _wait(proc, ex, seen, arrived, err)
        with contextlib.suppress(ProcessLookupError):  # what it left in the background
            os.killpg(proc.pid, signal.SIGKILL)
        if terminal is not None:
            reader.join(timeout=10)
            os.close(terminal[0])
        if isinstance(proc, Forked):
            FORKED_CPU[0] += proc.cpu
        out.seek(0)
        err.seek(0)
        stdout = b"".join(seen).decode(errors="replace") or out.read()
        stderr = err.read()
    if why is None and (proc.returncode != ex.exit or "Traceback" in stderr):
        why = f"exit {proc.returncode}, documented {ex.exit}"
    if why is None:
        return None
    tail = "\n      ".join((stderr.strip() or stdout.strip()).splitlines()[-4:])
    return f"{why}:\n      {tail}"


def _drain(fd: int, into: list[bytes], arrived: threading.Event) -> None:
    """Read a terminal's output until the program is gone (EIO on Linux)."""
    while True:
        try:
            data = os.read(fd, 65536)
        except OSError:
            data = b""
        if not data:
            arrived.set()
            return
        into.append(data)
        arrived.set()


ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
LIVE = re.compile(r"(\d+)/(\d+)\s+online\b.*?·\s*(\d+)\s+scans?\b", re.S)  # may wrap


def shown(terminal: str) -> bool:
    """Whether what a command that runs until stopped shows is on its terminal, so a
    person would now press Ctrl-C: the simulator's banner to its "Press Ctrl-C to
    stop."; a live table whose header counts a complete scan (or no device to poll: a
    gateway only); else (records, a report) a complete line."""
    text = ANSI.sub("", terminal).replace("\r", "")
    if text.startswith("Simulating "):
        return "Ctrl-C to stop." in text
    heads = LIVE.findall(text)
    if heads:
        return any(int(scans) > 0 or total == "0" for _, total, scans in heads)
    return "\n" in text


def _stderr_only(seen: list[bytes], err: IO[str]) -> bool:
    """Whether a command that shows nothing on its terminal has said something on stderr
    beyond what the set-up scripts say before they hand over (``setup: ...``, ``poll:
    no arguments ...``), which a loaded machine may print seconds before rtupoll runs."""
    if seen:
        return False
    fd = err.fileno()
    text = os.pread(fd, os.fstat(fd).st_size, 0).decode(errors="replace")
    return any(line and not line.startswith(("setup: ", "poll: "))
               for line in text.splitlines())


def _wait(proc: subprocess.Popen[str] | Forked, ex: Example, seen: list[bytes],
          arrived: threading.Event, err: IO[str]) -> str | None:
    """Let the example finish; one that runs until stopped gets Ctrl-C as soon as it
    has shown what it shows (``shown``; one silent on its terminal: once it said
    something on stderr and ``RUN_FOR`` has passed), as a person would press it."""
    if not ex.runs_until_stopped:
        try:
            proc.wait(timeout=CAP)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return f"still running after {CAP:.0f} s"
        return None
    start = time.monotonic()
    while proc.poll() is None:
        waited = time.monotonic() - start
        if waited > SHOWN_BY:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return f"showed nothing to stop on (a scan, a record, its banner) in {SHOWN_BY:.0f} s"
        if shown(b"".join(seen).decode(errors="replace")) or (
                waited > RUN_FOR and _stderr_only(seen, err)):
            break
        arrived.wait(0.1)
        arrived.clear()
    if proc.poll() is not None:
        return None  # it ended by itself: its status is checked as documented
    os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return "did not stop on Ctrl-C (SIGINT)"
    return None


def demo(where: Path) -> SimulatedLines:
    """The default demo (as ``poll --simulate`` and ``rtupoll simulate`` serve it), its
    lines linked as ``where/ttyUSB0`` and ``where/ttyUSB1``."""
    lines = simulated_lines()
    for line, name in zip(lines, PORTS.values(), strict=True):
        line.link = str(where / name)
    return lines


def run_block(block: Block, todo: list[Example], docfiles: dict[str, str], where: Path,
              forks: ForkServer | None = None) -> list[str]:
    where.mkdir(parents=True)
    for name, text in docfiles.items():
        (where / name).write_text(ported(text, where), encoding="utf-8")
    for name in ("profiles", "docs", "scripts", "tests"):
        (where / name).symlink_to(ROOT / name)
    failures = []
    with demo(where):
        for ex in todo:
            t0, c0 = time.monotonic(), _cpu()
            why = run(ex, where, docfiles, forks)
            if os.environ.get("RTUPOLL_DOCS_TIMES"):  # a file: where the time goes
                with open(os.environ["RTUPOLL_DOCS_TIMES"], "a", encoding="utf-8") as log:
                    log.write(f"{time.monotonic() - t0:6.1f} s {_cpu() - c0:6.2f} CPU-s  "
                              f"{ex.where}: {ex.command[:60]}\n")
            if why:
                failures.append(f"{ex.where}: {ex.command}\n    {why}")
    return failures


def _cpu() -> float:
    """CPU seconds of this process (the demo's threads) and its ended children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), \
        resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime + FORKED_CPU[0]


@pytest.fixture
def forks() -> Iterator[ForkServer | None]:
    """``rtupoll ARGS`` examples run forked from one server that imported rtupoll once
    (tests/forked_cli.py): the same command in a process of its own, without Python's
    and rtupoll's start-up each time. The rest (scripts, shell syntax) run with bash,
    and all of them where the server cannot wait for its children (no pidfd: not Linux).
    Asked for each test: a session of pytest run inside this process (pytester, with
    tests/conftest.py) closes this process's server as it ends, and the next test's is
    then a new one."""
    yield shared_server() if hasattr(os, "pidfd_open") else None


def doc_examples(doc: Path) -> Iterator[Example]:
    for b in blocks(doc):
        yield from examples(b)


def test_the_convention_is_read() -> None:
    """The parser itself, on a document written for it."""
    doc = ROOT / "tests" / "fixtures" / "examples.md"
    text = "\n".join([
        "```sh", "rtupoll read -p /dev/ttyUSB0 huiwen-aq@3   # a read",
        "rtupoll poll -c site.yaml --once  # one scan; exit: 9", "rtupoll read \\",
        "  -p /dev/ttyUSB1 co2meter-an117@4", "export X=1",
        "rtupoll write -p /dev/ttyUSB0 x@1 y=2   # needs: terminal", "```",
        "<!-- needs: hardware -->", "```console", "$ rtupoll scan -p /dev/ttyUSB0",
        "found", "```", "<!-- file: site.yaml -->", "```yaml", "port: /dev/ttyUSB0", "```"])
    got = []
    for b in _blocks_of(doc, text):
        got += [(e.line, e.command, e.needs, e.exit) for e in examples(b)]
    assert got == [
        (2, "rtupoll read -p /dev/ttyUSB0 huiwen-aq@3", None, 0),
        (3, "rtupoll poll -c site.yaml --once", None, 9),
        (4, "rtupoll read -p /dev/ttyUSB1 co2meter-an117@4", None, 0),
        (7, "rtupoll write -p /dev/ttyUSB0 x@1 y=2", "terminal", 0),
        (11, "rtupoll scan -p /dev/ttyUSB0", "hardware", 0)]
    assert files(_blocks_of(doc, text)) == {"site.yaml": "port: /dev/ttyUSB0\n"}


def _blocks_of(doc: Path, text: str) -> list[Block]:
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"rtupoll-doc-{os.getpid()}.md"
    tmp.write_text(text, encoding="utf-8")
    try:
        return [dataclasses.replace(b, doc=doc) for b in blocks(tmp)]
    finally:
        tmp.unlink()


def _runs_here(b: Block) -> tuple[list[Example], list[str]]:
    """A block's examples that can run here, and why the others cannot."""
    todo, skipped = [], []
    for ex in examples(b):
        if ex.needs:
            skipped.append(f"{ex.where}: needs {ex.needs}: {ex.command[:70]}")
        elif ex.command.startswith("scripts/") and not setup_is_current():
            skipped.append(f"{ex.where}: .venv setup not current: {ex.command[:70]}")
        else:
            todo.append(ex)
    return todo, skipped


WRITES_HERE = re.compile(r"(?:^|\s)(?:-o|--output|--write-config|--capture)[\s=](?!/)")
NAMES_A_FILE = re.compile(r"(?:^|\s)(?![\w.-]*/)([\w.-]+\.[a-z]{2,6})\b")


def _repeat_key(ex: Example, docfiles: dict[str, str]) -> tuple[str, ...] | None:
    """What an example proves, if that is nothing but its own text: no script, no
    shell syntax, no demo port (also in the documents' files it names), no other file
    of the working directory read or written. Such an example does the same wherever
    it is printed and leaves nothing that the examples after it see, so a repeat of it
    (README and a guide showing the same command) is the same proof; None otherwise."""
    uses = {n: t for n, t in docfiles.items() if n in ex.command}
    if ex.script or SHELL_SYNTAX.search(ex.command) or WRITES_HERE.search(ex.command):
        return None
    if any(dev in ex.command + "".join(uses.values()) for dev in PORTS):
        return None
    if any(name not in uses for name in NAMES_A_FILE.findall(ex.command)):
        return None
    return (ex.command, str(ex.exit), *(f"{n}\n{t}" for n, t in sorted(uses.items())))


@functools.cache
def _first_runs() -> dict[tuple[str, ...], str]:
    """Where each self-contained example runs first (README, then docs/ in order)."""
    first: dict[tuple[str, ...], str] = {}
    for doc in DOCS:
        for b in blocks(doc):
            for ex in _runs_here(b)[0]:
                if (key := _repeat_key(ex, _docfiles(doc))) is not None:
                    first.setdefault(key, ex.where)
    return first


@functools.cache
def _docfiles(doc: Path) -> dict[str, str]:
    """``files(blocks(doc))``, read once (each block of a document asks)."""
    return files(blocks(doc))


def _runnable(b: Block) -> tuple[list[Example], list[str]]:
    """A block's examples that run here, and why the others do not (they cannot, or
    they repeat a self-contained example that runs where it is printed first)."""
    todo, skipped = _runs_here(b)
    docfiles = _docfiles(b.doc)
    kept = []
    for ex in todo:
        key = _repeat_key(ex, docfiles)
        first = ex.where if key is None else _first_runs()[key]
        if first == ex.where:
            kept.append(ex)
        else:
            skipped.append(f"{ex.where}: runs as {first}: {ex.command[:70]}")
    return kept, skipped


# one test per block with examples that run here (each against its own demo), so the
# blocks of a long document spread over the test workers
BLOCKS = [b for doc in DOCS for b in blocks(doc) if _runnable(b)[0]]


def test_every_document_has_examples_that_run(capsys: pytest.CaptureFixture[str]) -> None:
    """The parametrisation below found the documents' examples (an empty list would
    pass vacuously), and says which cannot run here and why."""
    docs = {b.doc for b in BLOCKS}
    assert ROOT / "README.md" in docs
    assert len(docs) >= len(DOCS) - 2, sorted(str(d) for d in set(DOCS) - docs)
    skipped = [why for doc in DOCS for b in blocks(doc) for why in _runnable(b)[1]]
    with capsys.disabled():
        print("".join(f"\n  skipped {why}" for why in skipped), end="")


@pytest.mark.parametrize("block", BLOCKS,
                         ids=[f"{b.doc.relative_to(ROOT)}:{b.line}" for b in BLOCKS])
def test_every_example_works_as_printed(block: Block, tmp_path: Path,
                                        forks: ForkServer | None) -> None:
    todo, _ = _runnable(block)
    build()  # the profiles parsed once, here, before the demo's thread starts
    failures = run_block(block, todo, _docfiles(block.doc), tmp_path / "block", forks)
    assert not failures, f"{len(failures)} of {len(todo)} examples failed:\n" + \
        "\n".join(failures)


def _transcript(command: str, forks: ForkServer | None, where: Path, terminal: bool,
                stop: bool) -> tuple[int, str, str]:
    """Exit status, output and stderr of ``rtupoll ...`` started fresh by bash (``forks``
    None) or forked, on a terminal or not; one that runs until stopped (``stop``) gets
    Ctrl-C once it has shown what it shows, the others end by themselves."""
    env = examples_env()
    seen: list[bytes] = []
    arrived = threading.Event()
    tty = pty.openpty() if terminal else None
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, \
            open(os.devnull, "rb") as nothing:
        stdout = tty[1] if tty else out.fileno()
        argv = forkable(command)
        assert argv is not None
        proc: subprocess.Popen[bytes] | Forked = (
            forks.spawn(argv, where, env, nothing.fileno(), stdout, err.fileno()) if forks
            else subprocess.Popen(["bash", "-c", command], cwd=where, env=env, stdin=nothing,
                                  stdout=stdout, stderr=err, start_new_session=True))
        if tty is not None:
            os.close(tty[1])
            reader = threading.Thread(target=_drain, args=(tty[0], seen, arrived))
            reader.start()
        if stop:
            start = time.monotonic()
            while not shown(b"".join(seen).decode(errors="replace")) and proc.poll() is None \
                    and time.monotonic() - start < SHOWN_BY:
                arrived.wait(0.1)
                arrived.clear()
            os.killpg(proc.pid, signal.SIGINT)
        code = proc.wait(timeout=CAP)
        if tty is not None:
            reader.join(timeout=10)
            os.close(tty[0])
        out.seek(0)
        err.seek(0)
        text = b"".join(seen) or out.read()
        return code, text.decode(errors="replace"), err.read().decode(errors="replace")


@pytest.mark.parametrize(("command", "terminal", "stop"), [
    ("rtupoll decode 01 04 00 06 00 02 91 CA 01 04 04 00 00 A0 C1 42 14 --profile net-irnet-pro",
     False, False),
    ("rtupoll read -p ttyUSB9 huiwen-aq@3", False, False),  # no such port: exit 3, one line
    ("rtupoll profiles show huiwen-aq", True, False),  # rich on a terminal: colours, width
    ("rtupoll simulate huiwen-aq@3 --seed 1", True, True),  # Ctrl-C once it has started
], ids=["decode", "read-no-port", "profiles-show-on-a-terminal", "simulate-ctrl-c"])
def test_a_forked_command_is_a_fresh_one(command: str, terminal: bool, stop: bool,
                                         forks: ForkServer | None, tmp_path: Path) -> None:
    """What the examples' fork server runs is what a fresh ``rtupoll`` does: the same
    exit status, output and stderr (on a terminal too, stopped by Ctrl-C)."""
    if forks is None:
        pytest.skip("no fork server here (no pidfd): every example starts a fresh rtupoll")
    fresh = _transcript(command, None, tmp_path, terminal, stop)
    forked = _transcript(command, forks, tmp_path, terminal, stop)
    pts = re.compile(r"/dev/pts/\d+")  # each run's own pseudo-terminal
    assert [pts.sub("PTS", x) if isinstance(x, str) else x for x in forked] == \
        [pts.sub("PTS", x) if isinstance(x, str) else x for x in fresh]
    assert fresh[1].strip() or fresh[2].strip()  # (it said something to compare)
