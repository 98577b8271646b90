"""A real InfluxDB 1.x server for tests, on free 127.0.0.1 ports, its files in a temp dir.

    with Influx(tmp_path) as db:                  # or the ``influx`` fixture
        db.create("plant")
        status, body = db.write("plant", lines)   # HTTP /write: 204 when every line is in
        rows = db.query("plant", 'SELECT * FROM "rtupoll_reading"')   # the series, as dicts

The server is Debian's ``influxdb`` package (``influxd``), started with a config of its
own: HTTP on a free port with authentication off, data, meta and WAL directories
under the given path, no usage reporting, no ``_internal`` monitor database, logging
at ``warn`` into ``influxd.log`` there. ``close`` (the fixture does it after the test)
stops it. Import ``influx_fixture`` into a test module to use the fixture.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import pytest

from tests.brokers import free_port

INFLUXD = shutil.which("influxd") or "/usr/bin/influxd"

CONFIG = """\
reporting-disabled = true
bind-address = "127.0.0.1:{rpc}"

[meta]
  dir = "{root}/meta"
  logging-enabled = false

[data]
  dir = "{root}/data"
  wal-dir = "{root}/wal"
  query-log-enabled = false

[monitor]
  store-enabled = false

[subscriber]
  enabled = false

[continuous_queries]
  enabled = false

[http]
  enabled = true
  bind-address = "127.0.0.1:{http}"
  auth-enabled = false
  log-enabled = false
  flux-enabled = false

[logging]
  level = "warn"
  suppress-logo = true
"""


def have_influxd() -> bool:
    return Path(INFLUXD).exists()


class Influx:
    """One ``influxd`` process; ``url`` is its HTTP API."""

    def __init__(self, root: Path) -> None:
        self.root = root / "influxdb"
        self.root.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.config = self.root / "influxdb.conf"
        self.config.write_text(CONFIG.format(root=self.root, rpc=free_port(), http=self.port))
        self.log = self.root / "influxd.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen([INFLUXD, "run", "-config", str(self.config)],
                                         stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60  # a guard against a server that never comes up
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"influxd exited {self.proc.returncode}: "
                                   f"{self.log.read_text(errors='replace')[-2000:]}")
            try:
                with urllib.request.urlopen(self.url + "/ping", timeout=2) as r:
                    if r.status == 204:
                        return
            except OSError:
                pass
            time.sleep(0.1)
        raise RuntimeError("influxd did not answer /ping in 60 s")

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def __enter__(self) -> Influx:
        return self

    def __exit__(self, t: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # the HTTP API ------------------------------------------------------------

    def _request(self, path: str, params: dict[str, str], body: bytes | None = None
                 ) -> tuple[int, str]:
        url = f"{self.url}{path}?{urllib.parse.urlencode(params)}"
        req = urllib.request.Request(url, data=body, method="POST" if body is not None
                                     else "GET")
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return int(r.status), r.read().decode()
        except urllib.error.HTTPError as exc:
            return int(exc.code), exc.read().decode()

    def create(self, db: str) -> None:
        status, body = self._request("/query", {"q": f'CREATE DATABASE "{db}"'}, b"")
        assert status == 200 and '"error"' not in body, body

    def write(self, db: str, lines: str | list[str]) -> tuple[int, str]:
        """POST line protocol to /write (nanosecond timestamps): (HTTP status, body).
        204 means every line was stored; 400 names the first refused line's reason."""
        text = lines if isinstance(lines, str) else "".join(x + "\n" for x in lines)
        return self._request("/write", {"db": db, "precision": "ns"}, text.encode())

    def query(self, db: str, q: str) -> list[dict[str, Any]]:
        """One InfluxQL statement's series: each ``{"name", "tags", "columns", "values"}``."""
        status, body = self._request("/query", {"db": db, "q": q, "epoch": "ns"})
        assert status == 200, body
        result = json.loads(body)["results"][0]
        assert "error" not in result, result["error"]
        series: list[dict[str, Any]] = result.get("series", [])
        return series

    def field_types(self, db: str, measurement: str) -> dict[str, str]:
        """``SHOW FIELD KEYS``: field key -> float, integer, string or boolean."""
        out: dict[str, str] = {}
        for s in self.query(db, f'SHOW FIELD KEYS FROM "{measurement}"'):
            out.update({k: t for k, t in s["values"]})
        return out


@pytest.fixture(name="influx")
def influx_fixture(tmp_path: Path) -> Iterator[Influx]:
    if not have_influxd():
        pytest.fail("influxd is not installed (Debian: apt-get install influxdb)")
    db = Influx(tmp_path)
    try:
        yield db
    finally:
        db.close()
