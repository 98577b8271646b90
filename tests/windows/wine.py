"""rtupoll on Windows: the official embeddable CPython 3.13 (win_amd64) under Wine.

``scripts/windows-setup`` puts the runtime in ``.venv-windows/`` (the CPython, the
dependencies' Windows wheels and rtupoll's own wheel unpacked into its site-packages, a
Wine prefix); this runs commands there::

    with Wine(ports={"COM5": "/tmp/x/com5"}) as wine:   # COM5 opens the pty /tmp/x/com5 links to
        ran = wine.rtupoll("read", "-p", "COM5", "huiwen-aq@3")   # returncode, stdout, stderr
        proc = wine.popen("-m", "rtupoll", "poll", ...)           # a Popen, pipes for its streams

A Wine prefix's COM ports are the registry's ``HKLM\\Software\\Wine\\Ports`` values
(``COM5 = /unix/path``, any path a pty included, links followed when opened), read when
its wineserver starts: ``Wine`` sets them, then starts the prefix's wineserver and keeps
it (``-p``: every later start of a Windows process costs tens of milliseconds, not the
seconds of a server's start) until ``close``, which ends it with every Windows process
of the prefix. The first process after the server's start also starts Wine's services
(winedevice.exe, ...): that one is run with its standard streams on /dev/null, or the
services would keep a caller's pipes open (a ``subprocess.run`` that reads them to their
end would wait for the server's).

Wine gives a Windows process that the standard streams of the Unix one it starts in:
pipes, terminals and /dev/null work; a regular file does not (CPython stops at start
with "init_sys_streams: can't initialize sys standard streams ... [WinError 6] Invalid
handle"; Wine 8.0), so output goes to pipes (or to the command's own ``-o FILE``).
"""

from __future__ import annotations

import fcntl
import os
import re
import select
import shutil
import signal
import struct
import subprocess
import termios
import threading
import time
import tty
from collections.abc import Callable, Mapping
from pathlib import Path, PurePath
from types import TracebackType
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
HOME = ROOT / ".venv-windows"  # scripts/windows-setup's
PYTHON = HOME / "python" / "python.exe"
PREFIX = HOME / "prefix"
WINE = shutil.which("wine64") or "/usr/lib/wine/wine64"
WINESERVER = shutil.which("wineserver") or "/usr/lib/wine/wineserver"
PORTS_KEY = r"HKLM\Software\Wine\Ports"
# what Python on Windows writes to a pipe: the ANSI code page (Wine's is 1252 whatever
# the Unix locale, as a western Windows's); a console gets Unicode
ENCODING = "cp1252"


def winpath(path: str | PurePath) -> str:
    """The Windows name of a Unix path (Wine's drive Z: is /)."""
    return "Z:" + str(path).replace("/", "\\")


def environment(extra: Mapping[str, str | None] | None = None) -> dict[str, str]:
    """The environment of a Windows process: Wine's settings, then ``extra`` (None unsets)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env.update(WINEPREFIX=str(PREFIX), WINEDEBUG="-all", WINEDLLOVERRIDES="mscoree,mshtml=")
    for key, value in (extra or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return env


def setup() -> None:
    """Run scripts/windows-setup (quick when it has nothing to do)."""
    subprocess.run(["bash", str(ROOT / "scripts" / "windows-setup")], check=True,
                   stdin=subprocess.DEVNULL)


class Wine:
    """A Wine prefix's server with these COM ports, and commands run under it."""

    def __init__(self, ports: Mapping[str, str | PurePath] | None = None) -> None:
        self.ports = {name: str(path) for name, path in (ports or {}).items()}
        self.server: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Wine:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def start(self) -> None:
        quiet: dict[str, Any] = {"stdin": subprocess.DEVNULL, "stdout": subprocess.DEVNULL,
                                 "stderr": subprocess.DEVNULL, "env": environment()}
        subprocess.run([WINESERVER, "-k"], check=False, **quiet)  # (a server left over)
        subprocess.run([WINESERVER, "-w"], check=False, **quiet)
        for name, path in self.ports.items():  # (the registry, as a user would set it)
            subprocess.run([WINE, "reg", "add", PORTS_KEY, "/v", name, "/t", "REG_SZ", "/d",
                            path, "/f"], check=True, timeout=120, **quiet)
        subprocess.run([WINESERVER, "-k"], check=False, **quiet)
        subprocess.run([WINESERVER, "-w"], check=False, **quiet)
        self.server = subprocess.Popen([WINESERVER, "-f", "-p"], **quiet)
        # the services start with the first process: on /dev/null, not a caller's pipes
        subprocess.run([WINE, str(PYTHON), "-c", "pass"], check=True, timeout=120, **quiet)

    def close(self) -> None:
        if self.server is None:
            return
        subprocess.run([WINESERVER, "-k"], check=False, stdin=subprocess.DEVNULL,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       env=environment())
        try:
            self.server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.server.kill()
            self.server.wait()
        self.server = None

    def argv(self, *args: str) -> list[str]:
        return [WINE, str(PYTHON), *args]

    def popen(self, *args: str, env: Mapping[str, str | None] | None = None,
              stdin: Any = subprocess.DEVNULL, **kwargs: Any) -> subprocess.Popen[str]:
        """``python.exe ARGS`` under Wine; stdout and stderr are pipes unless given."""
        kwargs.setdefault("stdout", subprocess.PIPE)
        kwargs.setdefault("stderr", subprocess.PIPE)
        return subprocess.Popen(self.argv(*args), stdin=stdin, encoding=ENCODING,
                                env=environment(env), **kwargs)

    def run(self, *args: str, input: str | None = None, timeout: float = 120,
            env: Mapping[str, str | None] | None = None, cwd: str | Path | None = None,
            encoding: str = ENCODING) -> Ran:
        """``python.exe ARGS`` under Wine, to its end (its output decoded as ``encoding``:
        the code page's, unless the command was told otherwise, e.g. ``PYTHONUTF8=1``)."""
        start = time.monotonic()
        proc = subprocess.run(self.argv(*args), input=input, capture_output=True,
                              encoding=encoding, timeout=timeout, env=environment(env), cwd=cwd,
                              stdin=None if input is not None else subprocess.DEVNULL)
        return Ran(proc.returncode, proc.stdout, proc.stderr, time.monotonic() - start)

    def rtupoll(self, *args: str, **kwargs: Any) -> Ran:
        """``python.exe -m rtupoll ARGS`` under Wine (the Windows form of ``rtupoll``)."""
        return self.run("-m", "rtupoll", *args, **kwargs)

    def running(self, *args: str, **kwargs: Any) -> Running:
        """``python.exe -m rtupoll ARGS`` under Wine, left running (``Running``)."""
        return Running(self.popen("-m", "rtupoll", *args, **kwargs))


class Ran:
    """What a command did, as ``subprocess.CompletedProcess`` names it (and its wall time)."""

    def __init__(self, returncode: int, stdout: str, stderr: str, wall: float) -> None:
        self.returncode = returncode
        self.stdout = stdout
        self.stderr = stderr
        self.wall = wall

    def __repr__(self) -> str:
        return (f"Ran(returncode={self.returncode}, stdout={self.stdout[-2000:]!r}, "
                f"stderr={self.stderr[-2000:]!r})")


class Running:
    """A Windows command left running: its output lines as they come, ended by a Ctrl-C.

    Wine turns a SIGINT to the Unix process of a Windows console process into that
    process's CTRL_C_EVENT (CPython raises KeyboardInterrupt, as on Windows): that is
    the Ctrl-C sent here (``interrupt``)."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.proc = proc
        self.lines: list[str] = []
        self._seen = threading.Condition()
        self._pump = threading.Thread(target=self._read, daemon=True)
        self._pump.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._seen:
                self.lines.append(line.rstrip("\n"))
                self._seen.notify_all()
        with self._seen:
            self._seen.notify_all()

    def wait(self, match: Callable[[list[str]], bool], timeout: float = 60) -> list[str]:
        """The lines so far, once ``match(lines)`` holds (AssertionError after ``timeout``,
        a hang guard, or when the command ended first)."""
        deadline = time.monotonic() + timeout
        with self._seen:
            while not match(self.lines):
                left = deadline - time.monotonic()
                if left <= 0 or (not self._pump.is_alive()):
                    raise AssertionError(f"not printed: {self.lines[-20:]}; "
                                         f"exit {self.proc.poll()}; stderr: {self.stderr()}")
                self._seen.wait(min(left, 0.5))
            return list(self.lines)

    def stderr(self) -> str:
        if self.proc.poll() is None or self.proc.stderr is None:
            return "(running)"
        return self.proc.stderr.read()

    def interrupt(self, timeout: float = 60) -> tuple[int, str]:
        """Ctrl-C; then its exit code and standard error, once it ended."""
        self.proc.send_signal(signal.SIGINT)
        return self.end(timeout)

    def end(self, timeout: float = 60) -> tuple[int, str]:
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"did not end within {timeout} s of a Ctrl-C") from None
        self._pump.join(timeout=10)
        assert self.proc.stderr is not None
        return self.proc.returncode, self.proc.stderr.read()

    def __enter__(self) -> Running:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def screen(raw: bytes) -> str:
    """What a terminal shows of a Windows console's output, as text: Wine's escapes out,
    its line ends as ``\\n``."""
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", raw.decode(errors="replace"))
    return text.replace("\r\r\n", "\n").replace("\r", "")


class Console:
    """A Windows command on a console: a Unix pty as its standard streams, on which Wine
    runs the Windows console (what a person sees and types)::

        with Console(wine, "-m", "rtupoll", "set-address", ...) as term:
            term.expect("press Enter")     # what was shown since the last expectation
            term.type("\\r")               # Enter
    """

    def __init__(self, wine: Wine, *args: str, columns: int = 100, rows: int = 30) -> None:
        self.master, slave = os.openpty()
        # raw from the start, as Wine's console sets it once it reads: an Enter typed
        # before that would reach it as a line feed (Ctrl-J, not Enter) through ICRNL
        tty.setraw(slave)
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, columns, 0, 0))
        self.proc = subprocess.Popen(wine.argv(*args), stdin=slave, stdout=slave,
                                     stderr=slave, env=environment(), close_fds=True)
        os.close(slave)
        self.seen, self.done = b"", 0  # everything shown; how much of it was expected

    def expect(self, text: str, timeout: float = 60) -> str:
        """What was shown since the last expectation, up to ``text`` (lines joined: the
        console wraps them at its width)."""
        deadline = time.monotonic() + timeout
        while text not in screen(self.seen).replace("\n", "")[self.done:]:
            assert time.monotonic() < deadline, screen(self.seen)[-3000:]
            if select.select([self.master], [], [], 0.5)[0]:
                try:
                    self.seen += os.read(self.master, 4096)
                except OSError:  # it ended
                    break
        shown = screen(self.seen).replace("\n", "")
        at = shown.find(text, self.done)
        assert at >= 0, screen(self.seen)[-3000:]
        step, self.done = shown[self.done:at + len(text)], at + len(text)
        return step

    def type(self, text: str) -> None:
        os.write(self.master, text.encode())

    def interrupt(self) -> None:
        """Ctrl-C (as ``Running.interrupt``)."""
        self.proc.send_signal(signal.SIGINT)

    def close(self, timeout: float = 60) -> int:
        code = self.proc.wait(timeout=timeout)
        return code

    def __enter__(self) -> Console:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        os.close(self.master)
