"""Run ``rtupoll ARGS`` in a process of its own, forked from one that has imported
rtupoll already (a fork server), instead of a fresh interpreter each time.

A fresh ``rtupoll`` spends 0.1-0.3 CPU-s starting Python and importing rtupoll and its
libraries before it does anything; a test that runs many commands (the documents'
examples) pays that each time. Here a server process, started once, imports every
rtupoll module and then forks a child per command. The child is what a fresh
``rtupoll`` started by a shell would be: a process of its own in a session of its own
(``killpg(pid, SIGINT)`` is a Ctrl-C), the given stdin, stdout and stderr on fds 0-2
(``sys.stdout.isatty()`` is that of the new stdout, line-buffered on a terminal), the
given working directory, environment and ``sys.argv``, Python's own signal handlers,
and then the console script's two lines: ``sys.exit(main())``, with the interpreter's
normal exit after it (atexit, the threads, an uncaught KeyboardInterrupt ending it by
SIGINT). Its exit status and CPU time come back from the server, which waits for it.

What it does not show: that a fresh process can import what the command imports (the
server imported it all first). The CLI tests that start ``rtupoll`` itself
(tests/cli/test_*_imports.py among them) do; ``test_a_forked_command_is_a_fresh_one``
in tests/project/test_docs_examples.py compares the two on a few commands.

Usage::

    with ForkServer(env) as server:
        proc = server.spawn(["rtupoll", "read", ...], cwd, env, stdin, stdout, stderr)
        proc.wait(timeout=60)  # or proc.poll(); proc.returncode, proc.cpu
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType
from typing import Any

_MESSAGE = 1 << 20


class Forked:
    """A command the server forked: the part of ``subprocess.Popen`` a runner uses."""

    def __init__(self, server: ForkServer, pid: int) -> None:
        self._server = server
        self.pid = pid
        self.returncode: int | None = None
        self.cpu = 0.0  # its CPU seconds (user + system), once it has ended

    def poll(self) -> int | None:
        if self.returncode is None:
            self._server._collect(0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.returncode is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(str(self.pid), timeout or 0.0)
            self._server._collect(left)
        return self.returncode


class ForkServer:
    """One server process; ``spawn`` forks a command from it. Close it (``with``) to
    end the server (its CPU then counts in this process's children)."""

    def __init__(self, env: dict[str, str]) -> None:
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._proc = subprocess.Popen(
            [sys.executable, __file__, str(theirs.fileno())], env=env, pass_fds=[theirs.fileno()],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
        theirs.close()
        self._children: dict[int, Forked] = {}
        ready = self._receive(None)
        if ready.get("ready") is not True:
            raise RuntimeError(f"the fork server did not start: {ready}")

    def spawn(self, argv: list[str], cwd: Path | str, env: dict[str, str],
              stdin: int, stdout: int, stderr: int) -> Forked:
        """Fork ``argv`` (``["rtupoll", ...]``) with these fds as its 0, 1 and 2."""
        request = json.dumps({"argv": argv, "cwd": str(cwd), "env": env}).encode()
        socket.send_fds(self._sock, [request], [stdin, stdout, stderr])
        reply = self._receive(None)
        while "started" not in reply:  # (an earlier child's end)
            self._ended(reply)
            reply = self._receive(None)
        proc = Forked(self, reply["started"])
        self._children[proc.pid] = proc
        return proc

    def _receive(self, timeout: float | None) -> dict[str, Any]:
        if not select.select([self._sock], [], [], timeout)[0]:
            return {}
        data = self._sock.recv(_MESSAGE)
        if not data:
            raise RuntimeError(f"the fork server ended (status {self._proc.wait()})")
        message: dict[str, Any] = json.loads(data)
        return message

    def _collect(self, timeout: float | None) -> None:
        """Take in the children's ends that have come (waiting up to ``timeout``)."""
        message = self._receive(timeout)
        while message:
            self._ended(message)
            message = self._receive(0.0)

    def _ended(self, message: dict[str, Any]) -> None:
        proc = self._children.pop(message["ended"])
        proc.returncode, proc.cpu = message["status"], message["cpu"]

    def close(self) -> None:
        self._sock.close()  # the server sees the end, ends what is left of its children
        try:
            self._proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

    def __enter__(self) -> ForkServer:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.close()


# ---- the server process ------------------------------------------------------------

def _preload() -> None:
    """Import every rtupoll module (not ``__main__``, which would run the CLI)."""
    import importlib
    import pkgutil

    import rtupoll
    for module in pkgutil.walk_packages(rtupoll.__path__, "rtupoll."):
        if not module.name.endswith(".__main__"):
            importlib.import_module(module.name)


def _serve(sock: socket.socket) -> tuple[dict[str, Any], list[int]] | None:
    """Fork a child per request until the client closes; in a child, return its
    request (the child goes on to run it), in the server None at the end."""
    children: dict[int, int] = {}  # pidfd -> pid
    while True:
        ready: list[int] = select.select([sock.fileno(), *children], [], [])[0]
        for fd in ready:
            if fd == sock.fileno():
                data, fds, _, _ = socket.recv_fds(sock, _MESSAGE, 3)
                if not data:  # the client is done: what still runs is left over
                    for pidfd, pid in children.items():
                        with contextlib.suppress(ProcessLookupError):
                            os.killpg(pid, signal.SIGKILL)
                        os.waitpid(pid, 0)
                        os.close(pidfd)
                    return None
                pid = os.fork()
                if pid == 0:
                    sock.close()
                    for pidfd in children:
                        os.close(pidfd)
                    return json.loads(data), fds
                for received in fds:
                    os.close(received)
                children[os.pidfd_open(pid)] = pid
                sock.send(json.dumps({"started": pid}).encode())
            else:
                pid = children.pop(fd)
                os.close(fd)
                _, status, usage = os.wait4(pid, 0)
                sock.send(json.dumps({"ended": pid, "status": os.waitstatus_to_exitcode(status),
                                      "cpu": usage.ru_utime + usage.ru_stime}).encode())


def _become(request: dict[str, Any], fds: list[int]) -> None:
    """Make this forked child what a shell's fresh ``rtupoll`` would be."""
    os.setsid()
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
    for fd in fds:
        if fd > 2:
            os.close(fd)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    # sys.stdin/stdout/stderr now read and write the new fds 0-2; as at a fresh start,
    # stdout is line-buffered on a terminal only (stderr always)
    stdout = sys.stdout
    assert isinstance(stdout, io.TextIOWrapper)
    stdout.reconfigure(line_buffering=os.isatty(1))
    sys.argv = list(request["argv"])


if __name__ == "__main__":
    _preload()
    from rtupoll.cli import main
    server = socket.socket(fileno=int(sys.argv[1]))
    server.send(json.dumps({"ready": True}).encode())
    job = _serve(server)
    if job is None:
        sys.exit(0)
    _become(*job)
    del server, job
    # what the console script (.venv/bin/rtupoll) does
    sys.argv[0] = re.sub(r"(-script\.pyw|\.exe)?$", "", sys.argv[0])
    sys.exit(main())
