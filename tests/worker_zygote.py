"""pytest-xdist workers forked from one process that has imported what each of them
imports, instead of each started fresh (tests/README.md, "How fast").

A worker of ``pytest -n N`` starts a Python and imports pytest, xdist, hypothesis,
rtupoll and the peers' client libraries before it collects the tests: about half of its
start-up, N times over, while the run keeps both cores busy. With ``-n``
(tests/conftest.py) the process pytest was started as binds a Unix socket and starts one
*zygote*, which imports all that once, and gives the workers' specs (``popen``) this
file as their Python. execnet then starts ``PYTHON -I -S worker_zygote.py -u -c
BOOTSTRAP`` for each worker: the *client*, which hands its stdin, stdout and stderr, its
working directory, its environment and the ``-c`` code to the zygote and ends as the
worker the zygote forks for it ends, with its status. The worker is what ``PYTHON -u -c
BOOTSTRAP`` would be (the same fds, directory and environment, ``sys.argv`` and
``sys.path[0]`` as ``-c`` sets them, Python's signal handlers, unbuffered output, a
``__main__`` of its own), with the modules already imported. The zygote has also
collected the run's tests once (``pytest --collect-only`` with the run's arguments, its
output dropped): a worker finds the test files imported as pytest imports them, and
collects in 0.55 CPU-s instead of 1.2. Without pidfds (not Linux), with
``RTUPOLL_TEST_FRESH=1``, or where the socket cannot be made, conftest starts no zygote
and the workers start fresh; a client whose zygote is gone becomes that fresh Python
itself (``exec``).

The rtupoll commands the tests start are forked the same way, from one server for the
run that ``Listening`` starts too (tests/forked_cli.py).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import sys

ENV = "RTUPOLL_TEST_ZYGOTE"  # the zygote's socket, for the clients
_MESSAGE = 1 << 20
# what every worker imports before its first test, besides every rtupoll module; not the
# pytest plugins (xdist, pytest-timeout, hypothesis): pytest rewrites their asserts as
# it imports them, and warns of one imported already (``_collect`` imports them through
# pytest)
PRELOAD = ("pytest", "_pytest.pytester", "execnet", "jinja2", "prometheus_client", "yaml",
           "serial", "pymodbus.client", "rich.console", "click")


# ---- in the process pytest was started as --------------------------------------------

class Listening:
    """A server process for the run (``python FILE --listen FD ARGS``: this zygote, with
    the run's pytest arguments, or the shared rtupoll fork server of tests/forked_cli.py)
    on a Unix socket whose path is in the environment variable ``env`` (inherited by the
    workers). The socket is bound and listening before any client can start (one that
    connects while the server still imports waits in the backlog); the server ends when
    its stdin closes (``close``)."""

    def __init__(self, file: str, env: str, *args: str) -> None:
        import subprocess  # (here, not at the top: the client, this file too, stays small)
        import tempfile
        self._env = env
        self._where = tempfile.mkdtemp(prefix="rtupoll-server-")
        path = os.path.join(self._where, "socket")
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        listener.bind(path)
        listener.listen(64)
        self._proc = subprocess.Popen(
            [sys.executable, file, "--listen", str(listener.fileno()), *args],
            pass_fds=[listener.fileno()], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL)
        listener.close()
        os.environ[env] = path

    def stop(self) -> None:
        """Tell the server to end (``close`` waits for it: stop several, then close them,
        and they end side by side)."""
        os.environ.pop(self._env, None)
        assert self._proc.stdin is not None
        self._proc.stdin.close()

    def close(self) -> None:
        import shutil
        self.stop()
        self._proc.wait()
        shutil.rmtree(self._where, ignore_errors=True)


def spec(tx: str) -> str:
    """A worker's spec ``tx`` (``popen``) with this file's client as its Python."""
    if tx != "popen":
        return tx
    return "popen//python=" + " ".join([sys.executable, "-I", "-S", os.path.abspath(__file__)])


def available() -> bool:
    """Whether workers can be forked here (a space in a path would split the spec)."""
    return hasattr(os, "pidfd_open") and " " not in sys.executable + __file__ and \
        os.environ.get("RTUPOLL_TEST_FRESH") != "1"


def hold(path: str, owner: int) -> bool:
    """Wait until the file ``path`` exists (True), or until the process ``owner``, which
    is to make it, has ended (False: scripts/test was stopped). scripts/test's timing
    group starts while the parallel run runs and holds its first test this way."""
    import time
    try:
        ended = os.pidfd_open(owner)  # (readable once it has ended, reaped or not)
    except ProcessLookupError:
        return os.path.exists(path)
    except AttributeError:  # (no pidfds: not Linux)
        ended = -1
    try:
        while not os.path.exists(path):
            if ended < 0:
                try:
                    os.kill(owner, 0)
                except ProcessLookupError:
                    return os.path.exists(path)
                time.sleep(0.05)
            elif select.select([ended], [], [], 0.05)[0]:
                return os.path.exists(path)
        return True
    finally:
        if ended >= 0:
            os.close(ended)


# ---- the client (execnet's "python") ----------------------------------------------------

def _client(args: list[str]) -> None:
    """Have the zygote fork the worker ``args`` (``-u [-B] -c CODE``) asks for, and end
    as it ends; if it cannot, be that worker: exec a fresh Python with ``args``."""
    try:
        if args[-2:-1] != ["-c"] or not set(args[:-2]) <= {"-u", "-B"}:
            raise OSError(f"not a worker's arguments: {args}")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        sock.connect(os.environ[ENV])
        request = {"code": args[-1], "cwd": os.getcwd(), "env": dict(os.environ),
                   "bytecode": "-B" not in args}
        socket.send_fds(sock, [json.dumps(request).encode()], [0, 1, 2])
        started = sock.recv(_MESSAGE)
        if not started:
            raise OSError("the zygote closed the connection")
    except (OSError, KeyError):
        os.execv(sys.executable, [sys.executable, *args])
    # the worker has the pipes now: execnet sees them close when the worker ends
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)
    os.dup2(null, 1)
    pid = json.loads(started)["started"]
    # a SIGTERM for the worker's Python reaches the worker; a Ctrl-C reaches it anyway
    # (it is in the run's process group), and this one waits for it to end
    signal.signal(signal.SIGTERM, lambda n, _: os.kill(pid, n))
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    ended = sock.recv(_MESSAGE)
    code = json.loads(ended)["status"] if ended else 1
    if code < 0:  # ended by a signal: so does this
        signal.signal(-code, signal.SIG_DFL)
        os.kill(os.getpid(), -code)
    sys.exit(code)


# ---- the zygote --------------------------------------------------------------------

def preload_rtupoll() -> None:
    """Import every rtupoll module (not ``__main__``, which would run the CLI), and load
    the profile library: what this zygote and tests/forked_cli.py's server hold for the
    processes they fork. A forked process that loads a profile then finds the run's
    cache file already loaded (``rtupoll.config.compiled``): it only checks the
    profile's files, as any rtupoll process loading a profile again does."""
    import importlib
    import pkgutil

    import rtupoll
    for module in pkgutil.walk_packages(rtupoll.__path__, "rtupoll."):
        if not module.name.endswith(".__main__"):
            importlib.import_module(module.name)
    from rtupoll.config.library import load_library
    load_library()


def _preload(args: list[str]) -> None:
    import importlib
    for name in PRELOAD:
        with contextlib.suppress(ImportError):  # (a worker that needs it says why not)
            importlib.import_module(name)
    preload_rtupoll()
    if args:
        _collect(args)


def _collect(args: list[str]) -> None:
    """Collect the run's tests once, quietly (``args``: the run's pytest arguments): the
    test files, conftest.py and pytest's plugins are then imported as pytest imports them
    (asserts rewritten), and a worker's collection finds them imported (1.2 -> 0.55 CPU-s
    a worker). Whatever fails here, each worker collects (and reports it) as before."""
    import io

    import pytest
    quiet = io.StringIO()
    with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet), \
            contextlib.suppress(Exception, SystemExit):
        # no workers here (-n 0), nothing written to the cache
        pytest.main([*args, "--collect-only", "-q", "-n", "0", "-p", "no:cacheprovider"])


def _serve(listener: socket.socket) -> tuple[dict[str, object], list[int]] | None:
    """Fork a worker per client until stdin closes; in a worker, return its request."""
    children: dict[int, tuple[int, socket.socket]] = {}  # pidfd -> (pid, its client)
    while True:
        # one at a time: handling one closes and opens fds, which may reuse a number
        fd = select.select([0, listener.fileno(), *children], [], [])[0][0]
        if fd == 0:
            return None  # the run is over
        if fd != listener.fileno():
            pid, client = children.pop(fd)
            os.close(fd)
            _, status = os.waitpid(pid, 0)
            with contextlib.suppress(OSError):  # (a client killed: nobody to tell)
                client.send(json.dumps({"status": os.waitstatus_to_exitcode(status)}).encode())
            client.close()
            continue
        client, _ = listener.accept()
        data, fds, _, _ = socket.recv_fds(client, _MESSAGE, 3)
        if len(fds) != 3:  # (a client gone before it asked)
            for received in fds:
                os.close(received)
            client.close()
            continue
        pid = os.fork()
        if pid == 0:
            listener.close()
            client.close()
            for pidfd, (_, other) in children.items():
                os.close(pidfd)
                other.close()
            return json.loads(data), fds
        for received in fds:
            os.close(received)
        children[os.pidfd_open(pid)] = (pid, client)
        client.send(json.dumps({"started": pid}).encode())


def _become(request: dict[str, object], fds: list[int]) -> dict[str, object]:
    """Make this forked process what ``PYTHON -u -c CODE`` would start as; its globals."""
    import io
    import types
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
    for fd in fds:
        if fd > 2:
            os.close(fd)
    cwd, env = request["cwd"], request["env"]
    assert isinstance(cwd, str) and isinstance(env, dict)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    sys.dont_write_bytecode = not request["bytecode"]
    signal.signal(signal.SIGINT, signal.default_int_handler)
    # the encodings and error handlers Python's start-up chose for the zygote's own
    # (the same environment), unbuffered as -u has them
    for n, name in enumerate(("stdin", "stdout", "stderr")):
        was = getattr(sys, f"__{name}__")
        setattr(sys, name, io.TextIOWrapper(io.FileIO(n, "w" if n else "r", closefd=False),
                                            encoding=was.encoding, errors=was.errors,
                                            write_through=n > 0))
    sys.argv = ["-c"]
    sys.path[0] = ""
    main = types.ModuleType("__main__")
    sys.modules["__main__"] = main
    return main.__dict__


if __name__ == "__main__":
    if sys.argv[1:2] != ["--listen"]:
        _client(sys.argv[1:])
    # a worker exits as a forked rtupoll command does (flushed, collected, the status),
    # without tearing down the modules it shares with the zygote (tests/forked_cli.py)
    from forked_cli import ending, exit_unshared_last
    exit_unshared_last()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the run's to take
    server = socket.socket(fileno=int(sys.argv[2]))
    _preload(sys.argv[3:])
    import gc
    gc.collect()
    gc.freeze()  # (tests/forked_cli.py: a child's collections then copy no pages)
    job = _serve(server)
    if job is None:  # the run is over: nothing of this process's teardown shows, and
        os._exit(0)  # its heap is the run's largest (0.3 s the run's end waited for)
    code = job[0]["code"]
    assert isinstance(code, str)
    ending(lambda: exec(compile(code, "<string>", "exec"), _become(*job)))  # (what -c runs)
    sys.exit(0)
