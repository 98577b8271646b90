"""SIGHUP applies a changed ``http:``: the real ``rtupoll poll -c`` on the simulator, the
dashboard read over real HTTP. New authentication takes effect at once on the same
listener (event streams the old credentials opened are closed), a new address is bound
(the new listener first), an event stream opened before the move goes on, and an
address that cannot be bound refuses the reload in one line while the old listener and
its rules go on."""

from __future__ import annotations

import base64
import json
import signal
import socket
import time
from collections.abc import Callable
from pathlib import Path

from rtupoll.sim.runner import SimulatedBus
from tests.brokers import free_port, listening
from tests.web_helpers import Events, devices, get, get_json, running, until

TOKEN = "long-enough-token"
BASIC = {"Authorization": "Basic " + base64.b64encode(b"tech:correct-horse").decode()}
BEARER = {"Authorization": f"Bearer {TOKEN}"}


def site(path: Path, port: str, http: str | None) -> None:
    head = f"http:\n{http}" if http is not None else ""
    path.write_text(f"{head}buses:\n  - port: {port}\n    baudrate: 9600\n"
                    "    devices:\n      - {profile: huiwen-aq, address: 3, interval: 0.2}\n")


def test_sighup_applies_http_authentication_and_address_and_refuses_a_busy_one(
        sim: Callable[..., SimulatedBus], tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    path = tmp_path / "site.yaml"
    first, second = free_port(), free_port()
    site(path, bus.port, f"  listen: 127.0.0.1:{first}\n  users: {{tech: correct-horse}}\n")
    with running(["poll", "-c", str(path), "--format", "json", "--log-format", "json"],
                 tmp_path) as p:

        def log() -> list[str]:
            return [json.loads(x)["message"] for x in p.stderr().splitlines()
                    if x.startswith("{")]

        def reloads() -> list[str]:
            return [m for m in log() if m.startswith("reload")]

        def reload(line: str, *, settle: bool = False) -> list[str]:
            """SIGHUP; the reload's lines once ``line`` (the start of a line it must log)
            is among them; with ``settle`` 0.3 s more, for a test that no line follows."""
            before = len(reloads())
            p.proc.send_signal(signal.SIGHUP)
            until(lambda: any(m.startswith(line) for m in reloads()[before:]),
                  f"the reload's line {line!r}")
            if settle:
                time.sleep(0.3)  # the reload's other lines, if it had any
            return reloads()[before:]

        assert p.url == f"http://127.0.0.1:{first}/"
        assert get(p.url + "api/state")[0] == 401
        assert list(devices(get_json(p.url + "api/state", BASIC))) == ["huiwen-aq@3"]

        # the same address, a token instead of the user: at once, on the same listener;
        # an event stream the old credentials opened is closed
        before = Events(p.url, BASIC)
        assert next(iter(before))[0] == "state"
        site(path, bus.port, f"  listen: 127.0.0.1:{first}\n  token: {TOKEN}\n")
        lines = reload("reload: http: authentication changed")
        assert "reload: http: authentication changed" in lines, lines
        # the stream ends (open, reading it would fail on its 30 s socket timeout)
        assert set(e for e, _ in before) <= {"device", "buses", "ping"}
        before.close()
        assert get(p.url + "api/state", BASIC)[0] == 401
        assert get_json(p.url + "api/state", BEARER)["mode"] == "poll"
        stream = Events(p.url, BEARER)  # opened before the move below

        # a new address: bound, the old one closed, the open event stream goes on
        site(path, bus.port, f"  listen: 127.0.0.1:{second}\n  token: {TOKEN}\n")
        lines = reload("reload: http: dashboard on")
        assert (f"reload: http: dashboard on http://127.0.0.1:{second}/ "
                f"(no longer http://127.0.0.1:{first}/)") in lines, lines
        assert not listening(first)
        assert get_json(f"http://127.0.0.1:{second}/api/state", BEARER)["mode"] == "poll"
        assert get(f"http://127.0.0.1:{second}/api/state")[0] == 401
        events = iter(stream)
        assert next(events)[0] == "state"
        assert next(e for e, _ in events if e == "device") == "device"  # still flowing
        stream.close()

        with socket.socket() as taken:  # someone else holds the next address
            taken.bind(("127.0.0.1", 0))
            taken.listen()
            busy = taken.getsockname()[1]
            site(path, bus.port, f"  listen: 127.0.0.1:{busy}\n")
            lines = reload("reload refused", settle=True)
        assert len(lines) == 1 and lines[0].startswith(
            "reload refused, polling goes on unchanged: "), lines
        assert f"cannot listen on 127.0.0.1:{busy}" in lines[0]
        # the old listener and its token go on
        assert get(f"http://127.0.0.1:{second}/api/state")[0] == 401
        assert get_json(f"http://127.0.0.1:{second}/api/state", BEARER)["mode"] == "poll"

        # http: gone from the file: the dashboard stops listening; polling goes on
        site(path, bus.port, None)
        lines = reload("reload: http: no longer serving")
        assert (f"reload: http: no longer serving the dashboard on "
                f"http://127.0.0.1:{second}/") in lines, lines
        assert not listening(second)
        assert p.proc.poll() is None


def test_sighup_applies_new_limits_to_new_connections(sim: Callable[..., SimulatedBus],
                                                      tmp_path: Path) -> None:
    bus = sim("huiwen-aq@3")
    path = tmp_path / "site.yaml"
    port = free_port()
    site(path, bus.port, f"  listen: 127.0.0.1:{port}\n  max_connections: 2\n")
    with running(["poll", "-c", str(path), "--format", "json", "--log-format", "text"],
                 tmp_path) as p:
        held = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(2)]
        until(lambda: get(p.url + "api/state")[0] == 503, "the third refused at the cap")
        site(path, bus.port, f"  listen: 127.0.0.1:{port}\n  max_connections: 5\n"
                             "  hosts: [dash.example]\n")
        p.proc.send_signal(signal.SIGHUP)
        until(lambda: "reload: http: limits now header_timeout 10 s, idle_timeout 60 s, "
              "max_connections 5, hosts dash.example" in p.stderr(), "the reload's line")
        assert get(p.url + "api/state")[0] == 200
        assert get(p.url + "api/state", {"Host": "dash.example"})[0] == 200
        for s in held:
            s.close()
