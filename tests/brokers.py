"""A real mosquitto broker for tests, on a free 127.0.0.1 port, and mosquitto_sub to watch it.

    with Broker(tmp_path) as broker:              # or the ``broker`` fixture
        sub = broker.subscribe("rtupoll/#")       # a mosquitto_sub -v process
        ...
        msg = sub.wait(lambda m: m.topic == "rtupoll/air")
        broker.retained("rtupoll/bridge/state")   # the retained payload now, or None
        broker.stop(); broker.start()             # the same port again

The fixture is ``broker`` (import ``broker_fixture`` into a test module to use it).
``Broker(tmp_path, users={"gw": "secret"})`` refuses anonymous clients. Every process
started here is stopped by ``close`` (the fixture does it after the test).
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import pytest

MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening(port: int) -> bool:
    """Something accepts connections on 127.0.0.1:``port``."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False

def have_mosquitto() -> bool:
    return Path(MOSQUITTO).exists() and shutil.which("mosquitto_sub") is not None


@dataclass(frozen=True)
class Msg:
    topic: str
    payload: str
    retained: bool
    time: float  # time.time() when mosquitto_sub printed it


class Subscriber:
    """``mosquitto_sub`` on some topics; every message it prints, as it arrives."""

    def __init__(self, broker: Broker, topics: tuple[str, ...], *, user: str | None = None,
                 password: str | None = None) -> None:
        args = ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(broker.port), "-q", "1",
                "-F", "%r\t%t\t%p"]
        if user is not None:
            args += ["-u", user, "-P", password or ""]
        for t in topics:
            args += ["-t", t]
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                     text=True, bufsize=1)
        self.messages: list[Msg] = []
        self._lock = threading.Condition()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            retain, _, rest = line.rstrip("\n").partition("\t")
            topic, _, payload = rest.partition("\t")
            with self._lock:
                self.messages.append(Msg(topic, payload, retain == "1", time.time()))
                self._lock.notify_all()

    def wait(self, match: Callable[[Msg], bool], *, timeout: float = 60.0,
             after: int = 0) -> Msg:
        """The first message (from index ``after``) that matches; fails the test after
        ``timeout`` seconds without one."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                for m in self.messages[after:]:
                    if match(m):
                        return m
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = "\n".join(f"  {m.topic} {m.payload[:120]}"
                                     for m in self.messages[-15:])
                    pytest.fail(f"no matching MQTT message within {timeout:g} s; last seen:\n"
                                f"{seen}")
                self._lock.wait(left)

    def on(self, topic: str) -> list[Msg]:
        with self._lock:
            return [m for m in self.messages if m.topic == topic]

    def close(self) -> None:
        _end(self.proc)
        self._thread.join(timeout=10)  # the process is gone, so its output has ended
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def make_ca(where: Path, host: str) -> None:
    """A throw-away CA (``ca.pem``) and a server certificate for ``host`` it signed
    (``server.pem``, ``server.key``), with the openssl command-line tool."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed")

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=where, check=True, capture_output=True)

    # P-256 keys: as good a test of TLS as RSA's, and made in milliseconds (two RSA-2048
    # keys took 0.7 CPU-s)
    key = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    run("req", "-x509", *key, "-days", "2", "-subj", "/CN=rtupoll test CA", "-keyout", "ca.key",
        "-out", "ca.pem")
    run("req", *key, "-subj", f"/CN={host}", "-keyout", "server.key", "-out", "server.csr")
    (where / "san.ext").write_text(f"subjectAltName=IP:{host}\n")
    run("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
        "-CAcreateserial", "-days", "2", "-extfile", "san.ext", "-out", "server.pem")


class Broker:
    """mosquitto on 127.0.0.1 (no persistence: a restart forgets retained messages)."""

    def __init__(self, workdir: Path, *, users: dict[str, str] | None = None,
                 port: int | None = None, tls: bool = False) -> None:
        """``tls``: also a TLS listener on ``tls_port``, its CA in ``ca`` (``make_ca``)."""
        self.dir = workdir
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = port or free_port()
        self.tls_port = free_port() if tls else 0
        self.ca = self.dir / "ca.pem"
        self.users = users or {}
        self.proc: subprocess.Popen[bytes] | None = None
        self._subs: list[Subscriber] = []
        # as root, mosquitto would switch to its own user, who cannot read a test's files
        lines = [f"listener {self.port} 127.0.0.1", "persistence false",
                 f"user {pwd.getpwuid(os.getuid()).pw_name}",
                 f"allow_anonymous {'false' if self.users else 'true'}"]
        if self.users:
            pwfile = self.dir / "passwords"
            pwfile.write_text("")
            for user, password in self.users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(pwfile), user, password],
                               check=True, capture_output=True)
            pwfile.chmod(0o600)
            lines.append(f"password_file {pwfile}")
        if tls:
            make_ca(self.dir, "127.0.0.1")
            lines += [f"listener {self.tls_port} 127.0.0.1", f"cafile {self.ca}",
                      f"certfile {self.dir / 'server.pem'}",
                      f"keyfile {self.dir / 'server.key'}"]
        self.conf = self.dir / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n")
        self.log = self.dir / "mosquitto.log"

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> Broker:
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log,
                                         stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30  # a guard against a hang: listening ends it
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {self.log.read_text()[-500:]}")
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.port)) == 0:
                    return self
            time.sleep(0.02)
        raise RuntimeError(f"mosquitto did not listen on {self.port}")

    def stop(self) -> None:
        if self.proc is not None:
            _end(self.proc)
        self.proc = None

    def subscribe(self, *topics: str, user: str | None = None, password: str | None = None
                  ) -> Subscriber:
        sub = Subscriber(self, topics or ("#",), user=user, password=password)
        self._subs.append(sub)
        return sub

    def retained(self, topic: str, *, user: str | None = None, password: str | None = None
                 ) -> str | None:
        """The payload retained on ``topic`` now (None: nothing retained). Exact and quick:
        a marker published after subscribing comes back after any retained message."""
        import paho.mqtt.client as paho

        got: dict[str, str] = {}
        done = threading.Event()
        marker = f"tests/marker/{uuid.uuid4().hex}"

        def on_message(_client: object, _userdata: object, msg: paho.MQTTMessage) -> None:
            if msg.topic == marker:
                done.set()
            elif msg.retain:
                got[msg.topic] = msg.payload.decode()

        client = paho.Client(paho.CallbackAPIVersion.VERSION2)
        if user is not None:
            client.username_pw_set(user, password)
        client.on_message = on_message
        client.connect("127.0.0.1", self.port)
        client.loop_start()
        try:
            client.subscribe(topic, qos=1)
            client.subscribe(marker, qos=1)
            client.publish(marker, "x", qos=1)
            if not done.wait(10):
                pytest.fail(f"the broker did not echo the marker for {topic}")
        finally:
            client.disconnect()
            client.loop_stop()
        return got.get(topic)

    def close(self) -> None:
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        self.stop()

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


@pytest.fixture(name="broker")
def broker_fixture(tmp_path: Path) -> Iterator[Broker]:
    """A running mosquitto for one test (skipped where mosquitto is not installed)."""
    if not have_mosquitto():
        pytest.skip("mosquitto is not installed (scripts/test installs it)")
    b = Broker(tmp_path / "broker").start()
    try:
        yield b
    finally:
        b.close()


def _end(proc: subprocess.Popen[Any]) -> None:
    """Terminate ``proc`` (mosquitto, mosquitto_sub) and reap it; killed if it lingers."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
