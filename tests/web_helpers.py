"""Shared by the dashboard tests: a real ``rtupoll poll --http`` / ``rtupoll web`` process
(port 0: it says where it listens; forked from the fork server, or ``fresh``), HTTP and
server-sent-event clients (urllib), and the distribution's headless chromium driven by
selenium."""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from forked_cli import rtupoll_popen

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
ADDRESS = re.compile(r"on (http://[^\s]+/)")


class Proc:
    """A running rtupoll command whose stderr goes to a file; ``url`` once it listens."""

    def __init__(self, args: list[str], tmp: Path, *, name: str = "rtupoll",
                 fresh: bool = False) -> None:
        self.err_path = tmp / f"{name}.stderr"
        self._err = self.err_path.open("w")
        # forked from the fork server (tests/forked_cli.py), or a new interpreter
        popen = subprocess.Popen if fresh else rtupoll_popen
        self.proc = popen([sys.executable, "-m", "rtupoll", *args], stdout=subprocess.DEVNULL,
                          stderr=self._err)
        self.url = ""

    def stderr(self) -> str:
        return self.err_path.read_text()

    def wait_url(self, limit: float = 60.0) -> str:
        deadline = time.monotonic() + limit  # a guard against a hang, not a timing claim
        while time.monotonic() < deadline:
            m = ADDRESS.search(self.stderr())
            if m:
                self.url = m.group(1)
                return self.url
            if self.proc.poll() is not None:
                pytest.fail(f"rtupoll exited {self.proc.returncode}: {self.stderr()}")
            time.sleep(0.05)
        pytest.fail(f"rtupoll did not say where it listens: {self.stderr()}")

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._err.close()
        return code


@contextlib.contextmanager
def running(args: list[str], tmp: Path, *, name: str = "rtupoll", fresh: bool = False
            ) -> Iterator[Proc]:
    p = Proc(args, tmp, name=name, fresh=fresh)
    try:
        p.wait_url()
        yield p
    finally:
        p.stop()


@contextlib.contextmanager
def gateway_and_fleet(broker: str, port: str, device: str, tmp: Path, *, ident: str = "east"
                      ) -> Iterator[tuple[Proc, Proc]]:
    """A real gateway (``poll --mqtt --mqtt-id IDENT --http``, polling ``device`` on
    ``port``) and the fleet page (``web --mqtt``) on the same broker: (gateway, fleet)."""
    with running(["poll", "-p", port, "-b", "9600", "--format", "json", "-o",
                  str(tmp / f"{ident}.jsonl"), "--mqtt", broker, "--mqtt-id", ident,
                  "--http", "127.0.0.1:0", device], tmp, name=ident, fresh=True) as gateway, \
            running(["web", "--mqtt", broker, "--http", "127.0.0.1:0"], tmp, name="web",
                    fresh=True) as fleet:
        yield gateway, fleet


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    req = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def get_json(url: str, headers: dict[str, str] | None = None) -> Any:
    status, _, body = get(url, headers)
    assert status == 200, body
    return json.loads(body)


def until(check: Callable[[], Any], what: str, limit: float = 60.0, every: float = 0.1) -> Any:
    """Poll ``check`` until it returns something true (a guard against a hang)."""
    deadline = time.monotonic() + limit
    last: Any = None
    while time.monotonic() < deadline:
        # not there yet: a page still loading, a device not yet shown
        with contextlib.suppress(AssertionError, OSError, KeyError, IndexError, TypeError):
            last = check()
            if last:
                return last
        time.sleep(every)
    pytest.fail(f"{what}: not within {limit:g} s (last: {last!r})")


class Events:
    """An ``/api/events`` stream read line by line: (event, data) pairs."""

    def __init__(self, url: str, headers: dict[str, str] | None = None) -> None:
        req = urllib.request.Request(url + "api/events", headers=headers or {})
        self.resp = urllib.request.urlopen(req, timeout=30)

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        event, data = "message", ""
        for raw in self.resp:
            line = raw.decode().rstrip("\n")
            if not line:
                if data:
                    yield event, json.loads(data)
                event, data = "message", ""
            elif line.startswith("event: "):
                event = line[7:]
            elif line.startswith("data: "):
                data += line[6:]

    def close(self) -> None:
        self.resp.close()


def devices(state: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {d["key"]: d for gw in state["gateways"] for b in gw["buses"] for d in b["devices"]}


def field(state_or_device: dict[str, Any], name: str) -> dict[str, Any]:
    return next(f for f in state_or_device["fields"] if f["name"] == name)


def merge(state: dict[str, Any], event: dict[str, Any]) -> dict[str, Any] | None:
    """A ``device`` event into a snapshot, as docs/web.md says a client merges it (the
    page's merge, in app.js, is tested against ``/api/state`` in the browser); the
    merged device, or None for a device not in the snapshot."""
    delta = event["device"]
    dev = devices(state).get(delta["key"])
    if dev is None:
        return None
    index = {f["name"]: i for i, f in enumerate(dev["fields"])}
    for f in delta.get("fields", []):
        if f["name"] in index:
            i = index[f["name"]]
            dev["fields"][i] = {**dev["fields"][i], **f}
    for i, t in enumerate(delta.get("times") or []):
        if t is not None:
            dev["fields"][i]["time"] = t
    for k, v in delta.items():
        if k == "health":
            dev["health"].update(v)
        elif k not in ("fields", "times"):
            dev[k] = v
    return dev


def have_chromium() -> bool:
    return Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists() and \
        shutil.which("chromium") is not None


@contextlib.contextmanager
def chromium(width: int = 1280, height: int = 1000) -> Iterator[Any]:
    """The distribution's chromium, headless, with a new empty profile."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="rtupoll-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
              "--disable-background-networking", "--disable-component-update",
              "--disable-sync", "--disable-dev-shm-usage", f"--user-data-dir={profile}",
              f"--window-size={width},{height}"):
        opts.add_argument(a)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    try:
        driver.set_page_load_timeout(60)
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def console_errors(driver: Any) -> list[dict[str, Any]]:
    """The browser's errors, but the event stream's reconnection refused once the test's
    server is stopped (the page retries every 2 s; a slow teardown sees one or two)."""
    refused = "/api/events - Failed to load resource: net::ERR_CONNECTION_REFUSED"
    return [e for e in driver.get_log("browser")
            if e.get("level") == "SEVERE" and refused not in str(e.get("message"))]


def repainted(driver: Any) -> None:
    """Once the page has drawn two more frames (what a change of size or colour scheme
    needs to be shown: style, layout, the resize handler, paint), not after a fixed time."""
    driver.set_script_timeout(60)  # a guard against a hang, not a timing claim
    driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "requestAnimationFrame(() => requestAnimationFrame(() => done(true)));")


def color_scheme(driver: Any, scheme: str) -> None:
    driver.execute_cdp_cmd("Emulation.setEmulatedMedia", {
        "features": [{"name": "prefers-color-scheme", "value": scheme}]})


def phone(driver: Any, on: bool) -> None:
    if on:
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
            "width": 390, "height": 844, "deviceScaleFactor": 1, "mobile": True})
    else:
        driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
