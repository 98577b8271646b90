"""Run ``rtupoll ARGS`` in a process of its own, forked from one that has imported
rtupoll already (a fork server), instead of a fresh interpreter each time.

A fresh ``rtupoll`` spends 0.15-0.3 CPU-s starting Python and importing rtupoll and its
libraries before it does anything. Here a server process imports every rtupoll module
once and then forks a child per command: one for the whole run when pytest-xdist runs it
(started by tests/conftest.py before the workers, which connect to it), else one per
test process (``shared_server()``, started on first use, ended with the session). The
server keeps what it imported out of the garbage collector's sight (``gc.freeze``), so
that a child's collections do not copy every page of it, and a child exits without
tearing down the modules it shares with the server (``exit_unshared``): a forked
``rtupoll --version`` costs 0.03 CPU-s (0.18 with neither, 0.06 with the freeze alone).
The child is what a fresh ``rtupoll`` started by ``subprocess.Popen`` would be:

- a process and session of its own (``killpg(pid, SIGINT)`` is a Ctrl-C; a test need not
  ask for ``start_new_session``), with the given stdin, stdout and stderr on fds 0-2
  (``sys.stdout.isatty()`` is that of the new stdout, line-buffered on a terminal), the
  given working directory, environment, ``sys.argv`` and ``sys.path[0]``;
- the signal state of a fresh interpreter that has imported ``rtupoll.cli``: every
  handler as exec and Python's start-up leave it (ignored where the test process ignores
  it, else the default; SIGPIPE and SIGXFSZ ignored; SIGINT and SIGTERM rtupoll's early
  handler, one line and exit 130), the test thread's signal mask, no wakeup fd. The
  server blocks every signal across the fork, and the child unblocks them only once it
  is set up, so a signal sent at once (a Ctrl-C right after the start) is handled as a
  fresh process handles it, never lost nor taken by the server's handlers; the server
  says "started" only once the child has its own session, so ``killpg`` finds it;
- then what ``python -m rtupoll`` (``runpy``) or the console script (``sys.exit(main())``)
  does, and the interpreter's exit after it: the threads joined, the atexit callbacks,
  stdout and stderr flushed (exit 120 if stdout cannot be), the garbage collected (its
  finalizers), the status (an uncaught KeyboardInterrupt ending it by SIGINT). Only the
  modules' teardown is skipped (``exit_unshared``: the finalizer of an object a module
  still holds does not run).
  tests/cli/test_forked_cli.py compares that exit with Python's own. Its exit status and
  CPU time come back from the server, which waits for it.

``rtupoll_popen(args, ...)`` is ``subprocess.Popen`` for such a command (``args``:
``[sys.executable, "-m", "rtupoll", ...]`` or the console script's path first); pipes,
``communicate``, ``wait``, ``poll``, ``send_signal``, ``terminate``, ``kill``, ``pid``,
``returncode`` work as there. ``rtupoll_run`` is ``subprocess.run`` for one.

What it does not show: that a fresh process can import what the command imports, and
what Python does before ``main`` (the server did that once). What is about a fresh
process starts one (``subprocess.Popen``): start-up imports (tests/cli/test_*_imports.py),
an early Ctrl-C, packaging; ``test_a_forked_command_is_a_fresh_one`` in
tests/project/test_docs_examples.py compares the two. Variables that set up the
interpreter itself (``PYTHON*``) are the server's: a command given other ones starts
fresh. Without pidfds (not Linux), or with ``RTUPOLL_TEST_FRESH=1`` (the whole suite
as it was: every command a new interpreter), every command starts fresh.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import io
import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

_MESSAGE = 1 << 20
RTUPOLL = str(Path(sys.executable).with_name("rtupoll"))  # the console script
# every signal a handler can be set for (SIGKILL and SIGSTOP cannot have one)
_SIGNALS = sorted(s for s in signal.valid_signals() if s not in (signal.SIGKILL, signal.SIGSTOP))
SHARED = "RTUPOLL_TEST_FORK_SERVER"  # the socket of the run's server, if it has one
FORKED_CPU = [0.0]  # CPU seconds of the forked commands of this process that have ended


class Forked(subprocess.Popen[Any]):
    """``subprocess.Popen`` whose child the fork server forks instead of an exec: the same
    pipes, text mode, ``communicate``, ``wait``, ``poll`` and signals; ``cpu`` is the
    child's CPU seconds once it has ended."""

    cpu = 0.0

    def __init__(self, args: Sequence[str], *, server: ForkServer | None = None,
                 **kw: Any) -> None:
        self._server = server or shared_server()
        super().__init__(list(args), **kw)

    def _execute_child(self, args: list[str], executable: Any, preexec_fn: Any,
                       close_fds: bool, pass_fds: Sequence[int], cwd: Any,
                       env: Mapping[str, str] | None, startupinfo: Any, creationflags: int,
                       shell: bool, p2cread: int, p2cwrite: int, c2pread: int,
                       c2pwrite: int, errread: int, errwrite: int, *rest: Any) -> None:
        if executable is not None or preexec_fn is not None or shell or pass_fds:
            raise ValueError("a forked rtupoll takes args, stdio, cwd and env only")
        fds = [fd if fd != -1 else n for n, fd in enumerate((p2cread, c2pwrite, errwrite))]
        try:
            self.pid = self._server.fork(
                args, os.fspath(cwd) if cwd is not None else os.getcwd(),
                dict(os.environ if env is None else env), fds)
            self._child_created = True
        finally:
            self._close_pipe_fds(  # type: ignore[attr-defined]  # (CPython 3.11-3.13)
                p2cread, p2cwrite, c2pread, c2pwrite, errread, errwrite)

    def _internal_poll(self, _deadstate: int | None = None, *_: Any) -> int | None:
        if self.returncode is None:
            try:
                self._server.collect(0.0)
            except OSError:  # the server is gone (the session's end)
                if _deadstate is not None:
                    self.returncode = _deadstate
            self._take()
        return self.returncode

    def _wait(self, timeout: float | None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self._take() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            self._server.collect(left)
        assert self.returncode is not None
        return self.returncode

    def _take(self) -> int | None:
        if self.returncode is None:
            ended = self._server.ended(self.pid)
            if ended is not None:
                self.returncode, self.cpu = ended
                FORKED_CPU[0] += self.cpu
        return self.returncode


def rtupoll_popen(args: Sequence[str], **kw: Any) -> subprocess.Popen[Any]:
    """``subprocess.Popen(args, **kw)`` for ``[sys.executable, "-m", "rtupoll", ...]`` or
    ``[RTUPOLL, ...]``, forked from this process's server (module docstring); a fresh
    process where the server cannot stand in (no pidfd, other ``PYTHON*`` variables)."""
    if not _forkable(kw.get("env")):
        return subprocess.Popen(list(args), **kw)
    return Forked(args, **kw)


def rtupoll_run(args: Sequence[str], *, input: str | bytes | None = None,
                capture_output: bool = False, timeout: float | None = None,
                check: bool = False, **kw: Any) -> subprocess.CompletedProcess[Any]:
    """``subprocess.run`` with ``rtupoll_popen``."""
    if input is not None:
        kw["stdin"] = subprocess.PIPE
    if capture_output:
        kw["stdout"] = kw["stderr"] = subprocess.PIPE
    with rtupoll_popen(args, **kw) as proc:
        try:
            out, err = proc.communicate(input, timeout=timeout)
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        code = proc.poll()
        assert code is not None
    if check and code:
        raise subprocess.CalledProcessError(code, proc.args, out, err)
    return subprocess.CompletedProcess(proc.args, code, out, err)


def _forkable(env: Mapping[str, str] | None) -> bool:
    if not hasattr(os, "pidfd_open") or os.environ.get("RTUPOLL_TEST_FRESH") == "1":
        return False
    if env is None:
        return True
    mine = {k: v for k, v in os.environ.items() if k.startswith("PYTHON")}
    return {k: v for k, v in env.items() if k.startswith("PYTHON")} == mine


_SERVER: list[ForkServer] = []
_SERVER_LOCK = threading.Lock()


def shared_server() -> ForkServer:
    """This process's fork server, started on first use (``close_server`` ends it)."""
    with _SERVER_LOCK:
        if not _SERVER or _SERVER[0].closed:
            _SERVER[:] = [ForkServer(dict(os.environ))]
        return _SERVER[0]


def close_server() -> None:
    """End this process's fork server, if it started one (its CPU then counts in this
    process's children)."""
    with _SERVER_LOCK:
        for server in _SERVER:
            server.close()
        _SERVER.clear()


class ForkServer:
    """One server process; ``fork`` forks a command from it. Safe to share between
    threads. Close it (``with``) to end the server and what still runs of its children."""

    def __init__(self, env: dict[str, str]) -> None:
        self._proc: subprocess.Popen[bytes] | None = None
        if env.get(SHARED):  # the run's server (a client of it among the workers')
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            self._sock.connect(env[SHARED])
        else:  # one of its own
            self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            self._proc = subprocess.Popen(
                [sys.executable, __file__, str(theirs.fileno())], env=env,
                pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
            theirs.close()
        self.closed = False
        self._lock = threading.Condition()
        self._reading = False  # a thread is reading the socket (the others wait for it)
        self._sending = threading.Lock()
        self._next = 0
        self._started: dict[int, int | str] = {}  # request -> pid (or why not)
        self._ended: dict[int, tuple[int, float]] = {}  # pid -> (status, CPU-s)
        with self._sending:
            ready = self._read(None)
        if not ready or ready[0].get("ready") is not True:
            raise RuntimeError(f"the fork server did not start: {ready}")

    def spawn(self, argv: list[str], cwd: Path | str, env: dict[str, str],
              stdin: int, stdout: int, stderr: int) -> Forked:
        """Fork ``argv`` (the console script's path first) with these fds as its 0-2."""
        return Forked(argv, server=self, cwd=cwd, env=env, stdin=stdin, stdout=stdout,
                      stderr=stderr)

    def fork(self, args: list[str], cwd: str, env: dict[str, str], fds: list[int]) -> int:
        """Start ``args`` with ``fds`` as its 0, 1 and 2; its pid."""
        if args[1:3] == ["-m", "rtupoll"] and Path(args[0]).name.startswith("python"):
            how, argv = "module", ["-m", *args[3:]]
        elif Path(args[0]).name == "rtupoll":
            how, argv = "script", [str(a) for a in args]
        else:
            raise ValueError(f"not an rtupoll command: {args}")
        ignored = [s for s in _SIGNALS if signal.getsignal(s) == signal.SIG_IGN]
        mask = sorted(signal.pthread_sigmask(signal.SIG_BLOCK, []))
        with self._sending:
            self._next += 1
            request = self._next
            message = {"id": request, "how": how, "argv": argv, "cwd": cwd, "env": env,
                       "ignored": ignored, "mask": mask}
            socket.send_fds(self._sock, [json.dumps(message).encode()], fds)
        while request not in self._started:
            self.collect(None)
        started = self._started.pop(request)
        if isinstance(started, str):
            raise OSError(started)
        return started

    def ended(self, pid: int) -> tuple[int, float] | None:
        """The (exit status, CPU-s) of a child that has ended, taken once."""
        with self._lock:
            return self._ended.pop(pid, None)

    def collect(self, timeout: float | None) -> None:
        """Take in what the server said, waiting up to ``timeout`` for a word (while
        another thread reads, wait for it instead)."""
        with self._lock:
            if self._reading:
                self._lock.wait(timeout)
                return
            self._reading = True
        messages: list[dict[str, Any]] = []
        try:
            messages = self._read(timeout)
        finally:
            with self._lock:
                self._reading = False
                for message in messages:
                    if "started" in message:
                        self._started[message["id"]] = message["started"]
                    else:
                        self._ended[message["ended"]] = (message["status"], message["cpu"])
                self._lock.notify_all()

    def _read(self, timeout: float | None) -> list[dict[str, Any]]:
        if self.closed:
            raise OSError("the fork server is closed")
        out: list[dict[str, Any]] = []
        while select.select([self._sock], [], [], timeout if not out else 0.0)[0]:
            data = self._sock.recv(_MESSAGE)
            if not data:
                status = self._proc.wait() if self._proc else "unknown: the run's"
                raise RuntimeError(f"the fork server ended (status {status})")
            out.append(json.loads(data))
        return out

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._sock.close()  # the server sees the end, ends what is left of our children
        if self._proc is None:
            return
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

def _serve(sock: socket.socket, listening: bool) -> tuple[dict[str, Any], list[int]] | None:
    """Fork a child per request until the client closes (``listening``: for each client
    that connects to ``sock``, until stdin closes); in a child, return its request (the
    child goes on to run it), in the server None at the end. What a client leaves running
    when it closes is killed."""
    clients: dict[int, socket.socket] = {} if listening else {sock.fileno(): sock}
    children: dict[int, tuple[int, socket.socket]] = {}  # pidfd -> (pid, its client)
    try:
        while True:
            wait = [0, sock.fileno()] if listening else []
            # one at a time: handling one closes and opens fds, which may reuse a number
            fd = select.select([*wait, *clients, *children], [], [])[0][0]
            if fd in children:
                pid, client = children.pop(fd)
                os.close(fd)
                _, status, usage = os.wait4(pid, 0)
                with contextlib.suppress(OSError):  # (a client gone: nobody to tell)
                    client.send(json.dumps({
                        "ended": pid, "status": os.waitstatus_to_exitcode(status),
                        "cpu": usage.ru_utime + usage.ru_stime}).encode())
            elif listening and fd == 0:
                return None  # the run is over
            elif listening and fd == sock.fileno():
                client = sock.accept()[0]
                client.send(json.dumps({"ready": True}).encode())
                clients[client.fileno()] = client
            else:
                client = clients[fd]
                try:
                    data, fds, _, _ = socket.recv_fds(client, _MESSAGE, 3)
                except ConnectionResetError:  # the client was killed (a Ctrl-C, ...)
                    data, fds = b"", []
                if not data:  # the client is done: what still runs is left over
                    _kill([pid for pid, c in children.values() if c is client])
                    del clients[fd]
                    client.close()
                    if not listening:
                        return None
                    continue
                job = _fork(client, json.loads(data), fds, children, [sock, *clients.values()])
                if job is not None:
                    return job
    finally:
        if os.getpid() == _SERVER_PID:
            _kill([pid for pid, _ in children.values()])
            for pidfd in children:
                os.close(pidfd)


def _kill(pids: list[int]) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)


def _fork(sock: socket.socket, request: dict[str, Any], fds: list[int],
          children: dict[int, tuple[int, socket.socket]], sockets: list[socket.socket]
          ) -> tuple[dict[str, Any], list[int]] | None:
    """Fork the child of ``request`` (from the client ``sock``): in the child, its job
    (the server's ``sockets`` closed); in the server None, once the child has its own
    session (then ``started``)."""
    assert threading.active_count() == 1, "the fork server must stay one thread"
    settled, said = os.pipe()
    everything = signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())
    try:
        pid = os.fork()
    except OSError as error:
        signal.pthread_sigmask(signal.SIG_SETMASK, everything)
        for fd in (*fds, settled, said):
            os.close(fd)
        sock.send(json.dumps({"id": request["id"], "started": str(error)}).encode())
        return None
    if pid == 0:  # (every signal blocked until _become has set them)
        for other in sockets:
            other.close()
        for pidfd in children:
            os.close(pidfd)
        os.close(settled)
        request["said"] = said
        return request, fds
    signal.pthread_sigmask(signal.SIG_SETMASK, everything)
    os.close(said)
    for received in fds:
        os.close(received)
    os.read(settled, 1)  # (EOF: the child has its session, or has ended)
    os.close(settled)
    children[os.pidfd_open(pid)] = (pid, sock)
    sock.send(json.dumps({"id": request["id"], "started": pid}).encode())
    return None


def _become(request: dict[str, Any], fds: list[int]) -> None:
    """Make this forked child what ``subprocess.Popen`` would start fresh."""
    os.setsid()
    os.close(request["said"])  # the server may say "started": killpg(pid) finds us
    # the signals as exec and a fresh Python leave them, with rtupoll.cli imported
    from rtupoll.cli import _interrupted_early
    for s in _SIGNALS:
        signal.signal(s, signal.SIG_IGN if s in request["ignored"] else signal.SIG_DFL)
    for s in (signal.SIGPIPE, signal.SIGXFSZ):
        signal.signal(s, signal.SIG_IGN)
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _interrupted_early)
    signal.set_wakeup_fd(-1)
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
    # sys.path[0]: the working directory for ``-m``, the script's folder for a script
    sys.path[0] = os.getcwd() if request["how"] == "module" else \
        os.path.dirname(os.path.realpath(sys.argv[0]))
    signal.pthread_sigmask(signal.SIG_SETMASK, request["mask"])  # (what came is handled)


_SERVER_PID = os.getpid()
_ENDED: list[int | str] = []  # in a child: how its command ended (an exit status, "SIGINT")


def _status(code: object) -> int:
    """The exit status Python gives ``SystemExit(code)`` (for a code other than None or an
    int it prints the code first, and gives 1)."""
    if code is None:
        return 0
    return code if isinstance(code, int) else 1


def ending(command: Callable[[], object]) -> None:
    """Run a child's command, noting how it ends (for ``exit_unshared``); whatever it
    raises goes on to Python, as from a fresh ``rtupoll``."""
    try:
        command()
        _ENDED.append(0)
    except SystemExit as stop:
        _ENDED.append(_status(stop.code))
        raise
    except KeyboardInterrupt:
        _ENDED.append("SIGINT")
        raise
    except BaseException:
        _ENDED.append(1)
        raise


def exit_unshared() -> None:
    """A forked command's last atexit callback (registered before any other, in the
    server): what Python's exit still does after the callbacks that can show, then the exit
    itself, without tearing down the modules the child shares with the server. That
    teardown frees what the server imported, so it writes to (and the kernel copies)
    nearly every page the server filled: 45 ms of CPU a command (7,200 page faults), 7 CPU-s
    a run; nothing of it shows. What does show is done as Python does it: flush stdout,
    then stderr (unless closed), collect the garbage (a finalizer may print), flush them
    again; then exit with the command's status, or by SIGINT after an uncaught
    KeyboardInterrupt (130 if that does not end it). If a flush fails, this returns and
    Python's own exit runs, and says so as it does (exit 120)."""
    if not _ENDED:
        return  # the server, or a child that did not get to its command
    try:
        for collect in (True, False):
            for stream in (sys.stdout, sys.stderr):
                if stream is not None and not stream.closed:
                    stream.flush()
            if collect:
                gc.collect()
    except Exception:
        return
    if _ENDED[0] == "SIGINT":
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
        os._exit(130)
    os._exit(int(_ENDED[0]))


def exit_unshared_last() -> None:
    """Register ``exit_unshared`` as a server's first atexit callback, so that in a child
    it runs last; if one came before (it would not run), not at all."""
    atexit.register(exit_unshared)
    if getattr(atexit, "_ncallbacks", lambda: 0)() != 1:
        atexit.unregister(exit_unshared)


if __name__ == "__main__":
    exit_unshared_last()
    from worker_zygote import preload_rtupoll  # (this file's folder is sys.path[0])
    preload_rtupoll()
    from rtupoll.cli import main
    # what is imported stays: out of the collector's sight, a child's collections do not
    # touch (and so copy) every page the server filled (a forked `rtupoll --version` took
    # 0.18 CPU-s without, 0.06 with; 0.03 with exit_unshared too)
    gc.collect()
    gc.freeze()
    # a Ctrl-C for the whole test run is not the server's to take: the test process
    # closes it (and the server then ends the children)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    listening = sys.argv[1] == "--listen"  # the run's (tests/worker_zygote.Listening)
    sock = socket.socket(fileno=int(sys.argv[-1]))
    if not listening:
        sock.send(json.dumps({"ready": True}).encode())
    job = _serve(sock, listening)
    if job is None:  # the server's end (the zygote's, tests/worker_zygote.py)
        os._exit(0)
    _become(*job)
    how = job[0]["how"]
    del sock, job

    def command() -> None:
        if how == "module":  # what ``python -m rtupoll`` does
            import runpy
            runpy.run_module("rtupoll", run_name="__main__", alter_sys=True)
            sys.exit(0)
        # what the console script (.venv/bin/rtupoll) does
        sys.argv[0] = re.sub(r"(-script\.pyw|\.exe)?$", "", sys.argv[0])
        sys.exit(main())

    ending(command)
