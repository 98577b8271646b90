"""The dashboard's listener against hostile and broken clients, on real sockets, against
a real ``rtupoll poll --http``: half-sent and idle requests closed at their deadlines
while a normal client is served, the connection cap, a process out of file descriptors
(its limit lowered as systemd's ``LimitNOFILE`` would), Host and Origin on a loopback
bind (DNS rebinding), bytes that are not ASCII in the credentials, and malformed
requests: 400s and 401s, a line a minute on stderr, never a traceback.

The deadlines are set short here (a fraction of a second), so no test waits long; what
is asserted of them is a lower bound (a connection is never closed before its deadline)
and that it is closed (a guard of ``ANSWERED`` against a hang), never a wall-clock upper
bound a busy machine could miss."""

from __future__ import annotations

import base64
import contextlib
import http.client
import os
import resource
import shutil
import socket
import subprocess
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

import pytest
from conftest import ANSWERED

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import Broker, broker_fixture  # noqa: F401  (the broker fixture)
from tests.web_helpers import Proc, get_json, running, until
from tests.web_helpers import get as http_get

POLL = ["poll", "--format", "json", "--log-format", "text", "--interval", "0.5",
        "--timeout", "0.5"]
Dashboard = Callable[..., AbstractContextManager[Proc]]
HALF = b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nUser-Agent: slow"  # no end of headers


def where(p: Proc) -> tuple[str, int]:
    host, port = p.url.split("//")[1].rstrip("/").rsplit(":", 1)
    return host, int(port)


def connect(p: Proc) -> socket.socket:
    return socket.create_connection(where(p), timeout=ANSWERED)


def ask(p: Proc, request: bytes) -> bytes:
    """One raw request, the whole answer (the server closes: ``Connection: close``)."""
    with connect(p) as s:
        s.sendall(request)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out


def status(answer: bytes) -> int:
    return int(answer.split(b" ", 2)[1]) if answer.startswith(b"HTTP/") else 0


def get(path: str = "/api/state", *headers: str) -> bytes:
    head = "".join(f"{h}\r\n" for h in headers)
    if not any(h.lower().startswith("host:") for h in headers):
        head = "Host: 127.0.0.1\r\n" + head
    return f"GET {path} HTTP/1.1\r\n{head}Connection: close\r\n\r\n".encode("latin-1")


def closed_after(s: socket.socket) -> float:
    """Read until the server closes; the monotonic time it did."""
    s.settimeout(ANSWERED)  # a guard against a hang, not a timing claim
    try:
        while s.recv(65536):
            pass
    except ConnectionResetError:
        pass
    return time.monotonic()


@pytest.fixture
def dashboard(sim: Callable[..., SimulatedBus], tmp_path: Path
              ) -> Dashboard:
    bus = sim("huiwen-aq@3")

    def start(*options: str, listen: str = "127.0.0.1:0") -> AbstractContextManager[Proc]:
        return running([*POLL, "-p", bus.port, "--http", listen, *options, "huiwen-aq@3"],
                       tmp_path)
    return start


def no_traceback(p: Proc) -> str:
    err = p.stderr()
    assert "Traceback" not in err and "Error handling request" not in err, err
    return err


def test_half_sent_and_idle_connections_are_closed_at_their_deadlines(dashboard: Dashboard
                                                                     ) -> None:
    header, idle = 0.5, 1.0
    with dashboard("--http-header-timeout", str(header), "--http-idle-timeout",
                   str(idle)) as p:
        opened = time.monotonic()
        silent = [connect(p) for _ in range(20)]  # connect, send nothing
        half: list[tuple[socket.socket, float]] = []
        for _ in range(20):  # half a request: the headers never end
            s = connect(p)
            s.sendall(HALF)
            half.append((s, time.monotonic()))
        # a slow loris: a byte at a time, which must not push its deadline on
        loris = connect(p)
        first = time.monotonic()
        sent = 0
        # while they are held, a normal client is served
        assert status(ask(p, get())) == 200
        try:
            for byte in HALF * 100:
                loris.sendall(bytes([byte]))
                sent += 1
                time.sleep(0.01)
        except (BrokenPipeError, ConnectionResetError):
            pass
        assert sent < len(HALF) * 100  # closed long before it was done
        assert closed_after(loris) - first >= header
        for s, at in half:
            assert closed_after(s) - at >= header
        for s in silent:
            assert closed_after(s) - opened >= idle
        # a keep-alive client: answered, then idle, then closed
        with connect(p) as s:
            asked = time.monotonic()  # before its idle time can start: a lower bound
            s.sendall(get().replace(b"Connection: close", b"Connection: keep-alive"))
            assert status(s.recv(65536)) == 200
            assert closed_after(s) - asked >= idle
        for s in [*silent, loris, *(s for s, _ in half)]:
            s.close()
        assert status(ask(p, get())) == 200
    closed = [line for line in no_traceback(p).splitlines() if " closed " in line]
    # the 21 that sent part of a request, in one line and the counts at the stop (the
    # idle ones closed are no news)
    assert 1 <= len(closed) <= 2, closed
    assert sum(int(line.split(" closed ")[1].split()[0]) for line in closed) == 21
    assert all("with their headers not all in after 0.5 s" in line for line in closed)


def test_the_connection_cap_refuses_more_and_says_so_once(dashboard: Dashboard) -> None:
    with dashboard("--http-max-connections", "5", "--http-idle-timeout", "60") as p:
        held = [connect(p) for _ in range(5)]
        until(lambda: status(ask(p, get())) == 503, "the sixth connection refused")
        for _ in range(19):
            answer = ask(p, get())
            assert status(answer) == 503 and b"too many connections" in answer
        # a well-formed answer, as an HTTP client reads it
        conn = http.client.HTTPConnection(*where(p), timeout=ANSWERED)
        conn.request("GET", "/api/state")
        resp = conn.getresponse()
        assert (resp.status, resp.getheader("Retry-After"), resp.read()) == (
            503, "10", b"rtupoll: too many connections, retry later\n")
        conn.close()
        for s in held:
            s.close()
        until(lambda: status(ask(p, get())) == 200, "served again once they are closed")
        refused = [line for line in p.stderr().splitlines() if "refused" in line]
    assert len(refused) <= 2, refused  # the first, and the counts at the stop
    assert refused[0].endswith("at the connection cap (counted from now on, one line per "
                               "60 s)")
    no_traceback(p)


def test_out_of_file_descriptors_new_clients_are_served_once_the_hostile_ones_close(
        dashboard: Dashboard) -> None:
    """The process's limit lowered as a service manager's would be, the cap above it:
    the hostile connections take every descriptor; accept fails meanwhile (counted, a
    line, not a traceback per attempt); at their header deadline they are closed and a
    client waiting in the listen queue is served."""
    limit = 160
    with dashboard("--http-max-connections", "5000", "--http-header-timeout", "3",
                   "--http-idle-timeout", "3") as p:
        resource.prlimit(p.proc.pid, resource.RLIMIT_NOFILE, (limit, limit))
        used = len(os.listdir(f"/proc/{p.proc.pid}/fd"))
        hostile: list[socket.socket] = []
        for _ in range(limit - used + 40):  # more than it has descriptors left
            s = connect(p)
            s.sendall(HALF)
            hostile.append(s)
        # the process's table is full: a normal client waits in the listen queue
        until(lambda: len(os.listdir(f"/proc/{p.proc.pid}/fd")) >= limit - 1,
              "every descriptor taken")
        before = len(p.stderr())
        waiting = connect(p)
        waiting.sendall(get())
        asked = time.monotonic()
        answer = b""
        waiting.settimeout(60)  # the hostile ones are closed at 3 s: a guard
        while chunk := waiting.recv(65536):
            answer += chunk
        assert status(answer) == 200
        assert time.monotonic() - asked > 0  # served after it waited
        waiting.close()
        for s in hostile:
            s.close()
        assert status(ask(p, get())) == 200
        grew = p.stderr()[before:]
    err = no_traceback(p)
    assert "Too many open files" not in err
    lines = [line for line in grew.splitlines() if "refused" in line]
    assert len(lines) <= 2, grew  # counted: one line at the first, at most one a minute
    assert len(grew) < 1000, grew
    assert any("out of file descriptors (EMFILE)" in line for line in err.splitlines())


def test_host_and_origin_on_a_loopback_bind(dashboard: Dashboard
                                            ) -> None:
    with dashboard("--http-host", "dash.example") as p:
        port = where(p)[1]
        for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost", f"[::1]:{port}",
                     "app.localhost:9", f"dash.example:{port}", "DASH.EXAMPLE"):
            assert status(ask(p, get("/api/state", f"Host: {host}"))) == 200, host
        for host in (f"evil.example:{port}", "127.0.0.1.evil.example", "dash.example.evil"):
            answer = ask(p, get("/api/state", f"Host: {host}"))
            assert status(answer) == 421 and b"--http-host" in answer, host
        for origin in ("http://evil.example", f"http://evil.example:{port}", "null",
                       "http://[::1", "file://"):
            assert status(ask(p, get("/api/events", f"Origin: {origin}"))) == 403, origin
        for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}",
                       "https://dash.example"):
            assert status(ask(p, get("/api/state", f"Origin: {origin}"))) == 200, origin
        # the checks come before everything else: the page and /metrics too
        assert status(ask(p, get("/", "Host: evil.example"))) == 421
        assert status(ask(p, get("/metrics", "Host: evil.example"))) == 421
    no_traceback(p)


def test_beyond_loopback_any_name_reaches_it(dashboard: Dashboard
                                             ) -> None:
    from tests.brokers import free_port
    port = free_port()
    with dashboard("--http-token", "a-long-token", listen=f"0.0.0.0:{port}") as p:
        p.url = f"http://127.0.0.1:{port}/"
        assert status(ask(p, get("/api/state", "Host: dash.example",
                                 "Authorization: Bearer a-long-token"))) == 200


# bytes that are not ASCII, where a credential is read
RAW_AUTH = [b"Authorization: Bearer \xff\xfe\xfd", b"Authorization: Basic \xff\xfe",
            b"Authorization: Basic " + base64.b64encode(b"tech:\xff\xfe"),
            b"Authorization: Basic " + base64.b64encode("tech:corr\u00e9ct".encode()),
            b"Authorization: \xc3\xa9 x", b"Cookie: rtupoll_token=\xff\xfe",
            b"Cookie: \xff=\xfe; rtupoll_token=\"\xc3", b"Cookie: ;;;=;\x7f\x01"]
MALFORMED = {
    "no Host": b"GET /api/state HTTP/1.1\r\nConnection: close\r\n\r\n",
    "NUL in the path": b"GET /api/st\x00ate HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
    "huge headers": b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: " + b"a" * 20_000 + b"\r\n\r\n",
    # (aiohttp before 3.10 takes 500 headers, answers and keeps the connection: closed
    # here, so the answer ends)
    "many headers": b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n"
                    + b"X: y\r\n" * 500 + b"\r\n",
    "a bad chunk": b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nTransfer-Encoding: chunked\r\n\r\n"
                   b"zz\r\nxx\r\n",
    "HTTP/2's preface": b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n",
    "not HTTP": b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + b"\x00" * 40,
    "a bad method": b"G\xffT / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n",
    "a bad version": b"GET / HTTP/9.9\r\nHost: 127.0.0.1\r\n\r\n",
    "two lengths": b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 1\r\n"
                   b"Content-Length: 2\r\n\r\nab",
}


def test_hostile_requests_are_400_or_401_and_a_line_a_minute(
        dashboard: Dashboard) -> None:
    with dashboard("--http-token", "a-long-token", "--http-user", "tech:correct-horse") as p:
        for header in RAW_AUTH:
            answer = ask(p, b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n" + header +
                         b"\r\nConnection: close\r\n\r\n")
            assert status(answer) in (400, 401), (header, answer[:200])
        statuses = {}
        for _ in range(3):
            for what, request in MALFORMED.items():
                statuses[what] = status(ask(p, request))
        # the listener still serves the good ones
        answer = ask(p, get("/api/state", "Authorization: Bearer a-long-token"))
        assert status(answer) == 200
    err = no_traceback(p)
    assert "500" not in " ".join(str(s) for s in statuses.values())
    assert all(s in (400, 401, 0) for s in statuses.values()), statuses
    assert statuses["NUL in the path"] == statuses["a bad chunk"] == 400
    bad = [line for line in err.splitlines() if "request" in line and "refused" in line]
    # one line at the first bad request, and the counts of the rest when it stopped
    assert 1 <= len(bad) <= 2, err
    assert len(err) < 4000, err


# -- rtupoll web --mqtt: hostile retained messages on a real mosquitto --------------------

def test_the_fleet_viewer_survives_hostile_retained_messages(broker: Broker,
                                                            tmp_path: Path) -> None:
    import json

    def publish(topic: str, payload: str | bytes, retain: bool = True) -> None:
        subprocess.run(["mosquitto_pub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                        *(["-r"] if retain else []), "-t", topic, "-s"],
                       input=payload.encode() if isinstance(payload, str) else payload,
                       check=True, timeout=30)

    huge = "9" * 400
    probe = {"profile": "probe", "address": 1, "bus": "line1", "fields": {
        "temperature": {"label": "temperature", "unit": "°C", "kind": "number",
                        "precision": 1}}}
    publish("rtupoll/good/bridge/info", json.dumps({"gateway": "good", "devices": {
        "probe": probe}}))
    publish("rtupoll/good/probe", json.dumps({"temperature": 21.5}))
    # the hostile ones: a precision of 10^8, a 400-digit number, not JSON, wrong types,
    # a device whose state is a list, 900 kB for a gateway nobody knows
    publish("rtupoll/bad/bridge/info", json.dumps({"gateway": "bad", "devices": {
        "d": {"fields": {"v": {"kind": "number", "precision": 100_000_000},
                         "w": {"kind": "number", "precision": int(huge)}}}}}))
    publish("rtupoll/bad/d", f'{{"v": 1.25, "w": {huge}}}')
    publish("rtupoll/worse/bridge/info", f'{{"gateway": {huge}, "devices": [')
    publish("rtupoll/worst/bridge/info", '{"devices": {"x": 5}, "version": [1, 2]}')
    publish("rtupoll/worst/x", "[1, 2, 3]")
    publish("rtupoll/nobody/thing", b"x" * 900_000)
    with running(["web", "--mqtt", broker.url, "--http", "127.0.0.1:0"], tmp_path,
                 name="web") as p:
        def fields() -> dict[str, str]:
            state = get_json(p.url + "api/state")
            return {f"{d['key']}/{f['name']}": f["text"] for g in state["gateways"]
                    for b in g["buses"] for d in b["devices"] for f in d["fields"]}

        got = until(lambda: (f := fields()).get("rtupoll/good/probe/temperature") == "21.5"
                    and f.get("rtupoll/bad/d/v") and f, "the good gateway's reading")
        assert got["rtupoll/bad/d/v"] == "1.250000"  # 6 decimals at most
        assert got["rtupoll/bad/d/w"] == "not published" or len(got["rtupoll/bad/d/w"]) < 40
        status_, _, body = http_get(p.url + "api/state")
        assert status_ == 200 and len(body) < 20_000
        # live, hostile and good in turn: each good one is shown, the session stays
        for i in range(3):
            publish("rtupoll/bad/d", f'{{"v": {huge}}}'.encode(), retain=False)
            publish("rtupoll/bad/d", b"{\xff not json", retain=False)
            publish("rtupoll/good/probe", json.dumps({"temperature": 30.5 + i}),
                    retain=False)
            want = f"{30 + i}.5"
            until(lambda want=want: fields().get("rtupoll/good/probe/temperature") == want,
                  f"the good reading {want}")
        assert get_json(p.url + "api/state")["broker"] == "connected"
    err = p.stderr()
    assert "Traceback" not in err and "reconnecting" not in err and "lost" not in err, err
    dropped = [line for line in err.splitlines() if "dropped" in line]
    assert 1 <= len(dropped) <= 2, err  # one line, and the counts of the rest at the stop


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll is not installed "
                    "(scripts/test installs it)")
def test_half_open_dashboard_connections_leave_the_gateway_its_clients(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    """The issue's case: systemd's usual limit of 1,024 descriptors, 1,100 connections
    that each sent half a request. At the dashboard's cap the rest are refused, so the
    gateway's listener beside it still takes a Modbus TCP client (mbpoll)."""
    from tests.brokers import free_port
    bus = sim("huiwen-aq@3")
    bus.set(3, "co2", 777)
    serve = free_port()
    with running([*POLL, "-p", bus.port, "--serve", f"127.0.0.1:{serve}", "--http",
                  "127.0.0.1:0", "huiwen-aq@3"], tmp_path) as p:
        resource.prlimit(p.proc.pid, resource.RLIMIT_NOFILE, (1024, 1024))
        hostile = []
        try:
            for _ in range(1100):
                s = connect(p)
                with contextlib.suppress(OSError):  # refused at the cap: reset
                    s.sendall(HALF)
                hostile.append(s)
            done = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(serve), "-1", "-o", "2",
                                   "-a", "3", "-t", "3", "-r", "30009", "-0", "-c", "1",
                                   "127.0.0.1"], capture_output=True, text=True, timeout=60)
            assert done.returncode == 0 and "777" in done.stdout, done.stdout + done.stderr
            fds = len(os.listdir(f"/proc/{p.proc.pid}/fd"))
            assert fds < 1024 - 400, fds  # the cap (256) and the 503s' short linger
        finally:
            for s in hostile:
                s.close()
        until(lambda: status(ask(p, get())) == 200, "the dashboard serves again")
    err = no_traceback(p)
    refused = [line for line in err.splitlines() if "--http" in line and "refused" in line]
    assert len(refused) <= 2, err  # the first, and the counts at the stop
    assert 0 < sum(int(line.split(" refused ")[1].split()[0]) for line in refused) <= 1100 - 256


def server_side(server_at: tuple[str, int], client: socket.socket) -> str | None:
    """The kernel's TCP state (``/proc/net/tcp``, hex: 01 established, 04 closed with data
    still queued) of the listener's end of ``client``'s connection; None: gone."""
    def hexed(host: str, port: int) -> str:
        return f"{socket.inet_aton(host)[::-1].hex().upper()}:{port:04X}"

    server, me = hexed(*server_at), hexed(*client.getsockname())
    with open("/proc/net/tcp") as f:
        for line in f.read().splitlines()[1:]:
            fields = line.split()
            if fields[1] == server and fields[2] == me:
                return fields[3]
    return None


def test_a_client_that_never_reads_is_reset_its_buffers_freed(dashboard: Dashboard
                                                               ) -> None:
    """Requests pipelined, their answers never read (a small receive buffer): the
    answers fill the kernel's queue, then the listener's; after ``idle_timeout`` of that
    the connection is reset, so neither the process nor the kernel keeps the megabytes
    of answers. Other clients are served meanwhile."""
    with socket.create_server(("127.0.0.1", 0)) as listener, \
            socket.create_connection(listener.getsockname()) as c:
        assert server_side(listener.getsockname(), c) == "01"  # the helper sees a socket
    with dashboard("--http-idle-timeout", "1") as p:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.settimeout(ANSWERED)
        s.connect(where(p))
        # 400 requests (26 kB: under the bound of a request's headers) for 9 MB of the
        # page's script, more than the kernel's buffers take
        request = get("/static/app.js").replace(b"Connection: close",
                                                b"Connection: keep-alive")
        s.sendall(request * 400)
        assert status(ask(p, get())) == 200
        until(lambda: server_side(where(p), s) is None, "the listener's end reset and gone")
        with pytest.raises(ConnectionResetError):
            while s.recv(65536):
                pass
        s.close()
        assert status(ask(p, get())) == 200
    closed = [line for line in no_traceback(p).splitlines() if " closed " in line]
    assert [line.split(": ", 1)[1] for line in closed] == [
        "closed 1 connection: 1 not reading what they were sent for 1 s (counted from now "
        "on, one line per 60 s)"]


def rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS:")).split()[1])


def test_the_bytes_of_a_requests_headers_are_bounded(dashboard: Dashboard) -> None:
    """aiohttp alone holds up to 128 header lines of 8 kB each while they come (200
    such half-sent requests: 385 MB); the listener takes 32 kB of headers a request."""
    line = b"X-Padding: " + b"a" * 8000 + b"\r\n"
    with dashboard("--http-header-timeout", "60") as p:
        assert status(ask(p, get())) == 200
        before = rss_kb(p.proc.pid)
        held = []
        for _ in range(200):  # just under the bound, and never ended
            s = connect(p)
            s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n" + line * 3)
            held.append(s)
        assert status(ask(p, get())) == 200  # every one of them read by now
        grew = rss_kb(p.proc.pid) - before
        # over the bound: refused at once, 431 (or a reset, its request unread)
        with connect(p) as s:
            try:
                s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n" + line * 20)
                answer = s.recv(65536)
            except (BrokenPipeError, ConnectionResetError):
                answer = b""
            assert answer == b"" or status(answer) == 431, answer[:100]
        for s in held:
            s.close()
    assert grew < 40_000, f"{grew} kB for 200 half-sent requests of 24 kB"
    assert "closed 1 connection: 1 with more than 32 kB of headers" in no_traceback(p)
