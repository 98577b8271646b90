"""``rtupoll.refusals``: a listener's refused connections counted and logged once per
interval, and asyncio's accept errors (out of file descriptors) routed there instead of
a traceback each, in a real process whose descriptors run out on real sockets."""

from __future__ import annotations

import asyncio
import logging
import re
import resource
import socket
import subprocess
import sys
import textwrap
from typing import Any

import pytest

from rtupoll.refusals import Refusals, reason, watch


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_first_refusal_is_logged_then_one_line_per_interval(
        caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    r = Refusals("--http 127.0.0.1:8080", logging.getLogger("rtupoll.test"), every=60,
                 clock=clock)
    with caplog.at_level(logging.WARNING, "rtupoll.test"):
        r.refused("cap")
        for _ in range(500):
            clock.now += 0.1
            r.refused("EMFILE")
        r.refused("cap")
        clock.now += 20  # 70 s after the first line
        r.refused("EMFILE")
        r.flush()  # nothing left: no line
    lines = [rec.getMessage() for rec in caplog.records]
    assert lines == [
        "--http 127.0.0.1:8080: refused 1 connection: 1 at the connection cap (counted "
        "from now on, one line per 60 s)",
        # nothing more within 60 s of it; the next refusal after that: the counts since
        "--http 127.0.0.1:8080: refused 502 connections in the last 70 s: 501 out of file "
        "descriptors (EMFILE), 1 at the connection cap"]
    assert r.total == 503 and r.counts == {"EMFILE": 501, "cap": 2}
    assert all(rec.exc_info is None for rec in caplog.records)


def test_counts_left_when_refusals_stop_are_logged_at_the_intervals_end(
        caplog: pytest.LogCaptureFixture) -> None:
    async def main() -> None:
        r = Refusals("gw", logging.getLogger("rtupoll.test"), every=0.05)
        r.refused("cap")
        r.refused("cap")
        r.refused("EMFILE")
        await asyncio.sleep(0.3)  # the timer's line comes after 0.05 s

    with caplog.at_level(logging.WARNING, "rtupoll.test"):
        asyncio.run(main())
    lines = [rec.getMessage() for rec in caplog.records]
    assert len(lines) == 2, lines
    assert re.fullmatch(r"gw: refused 2 connections in the last 0\.0\d* s: 1 at the "
                        r"connection cap, 1 out of file descriptors \(EMFILE\)", lines[1]), lines


def test_other_contexts_go_to_the_handler_before() -> None:
    seen: list[dict[str, Any]] = []

    async def main() -> int:
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(lambda _loop, ctx: seen.append(ctx))
        r = Refusals("x", logging.getLogger("rtupoll.test"))
        with socket.socket() as listening, socket.socket() as other:
            unwatch = watch([listening], r)
            err = OSError(24, "Too many open files")
            loop.call_exception_handler({"message": "m", "exception": err,
                                         "socket": listening})
            loop.call_exception_handler({"message": "m", "exception": err, "socket": other})
            loop.call_exception_handler({"message": "no socket"})
            unwatch()
            loop.call_exception_handler({"message": "m", "exception": err,
                                         "socket": listening})
            watch([listening], r)  # a second watch keeps the one handler
            assert loop.get_exception_handler().before is not None  # type: ignore[union-attr]
        return r.total

    assert asyncio.run(main()) == 1
    assert [c["message"] for c in seen] == ["m", "no socket", "m"]
    assert reason(OSError(24, "x")) == "EMFILE" and reason(OSError()) == "OSError"


CHILD = textwrap.dedent("""
    import asyncio, logging, sys
    from rtupoll.refusals import Refusals, watch

    logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(message)s")

    class Held(asyncio.Protocol):
        def connection_made(self, t):
            t.write(b"hello\\n")

    async def main():
        loop = asyncio.get_running_loop()
        server = await loop.create_server(Held, "127.0.0.1", 0)
        refusals = Refusals("test", logging.getLogger("t"))
        watch(server.sockets, refusals)
        print(server.sockets[0].getsockname()[1], flush=True)
        await loop.run_in_executor(None, sys.stdin.readline)
        print(refusals.total, flush=True)

    asyncio.run(main())
""")


def test_a_process_out_of_descriptors_logs_one_line_not_a_traceback_each() -> None:
    def low_limit() -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))

    child = subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=low_limit)
    assert child.stdout is not None and child.stdin is not None
    held: list[socket.socket] = []
    try:
        port = int(child.stdout.readline())
        # more connections than the child has descriptors: the first ~55 are taken
        # (each says hello), the rest wait in the listen queue while accept fails
        for _ in range(120):
            held.append(socket.create_connection(("127.0.0.1", port), timeout=10))
        held[0].recv(6)
        out, err = child.communicate("\n", timeout=60)
    finally:
        for s in held:
            s.close()
        if child.poll() is None:
            child.kill()
            child.wait()
    assert int(out.split()[-1]) >= 1  # refusals were counted ...
    assert "Traceback" not in err and "Too many open files" not in err
    assert err.splitlines() == ["test: refused 1 connection: 1 out of file descriptors "
                                "(EMFILE) (counted from now on, one line per 60 s)"]
