"""``poll -o``: whole records or nothing. On a full disk (a file size limit stands in for
it) the file output stops with one logged error, the file holds whole lines only, and
the gateway goes on answering (mbpoll); a partial last line an earlier run left is cut
off before anything is appended; SIGHUP resumes."""

from __future__ import annotations

import json
import logging
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_runner import rtupoll
from conftest import ANSWERED
from forked_cli import rtupoll_popen

from rtupoll.ui.outfile import OutputFile
from tests.brokers import free_port

# a child under a file-size limit must not write Python's bytecode cache: the interpreter
# renames a .pyc cut short by the limit into place, and every later rtupoll start that
# imports that module then fails (EOFError)
NO_BYTECODE = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}

LIMIT = 4000


def limited() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT, LIMIT))


def whole_json_lines(path: Path) -> list[dict[str, object]]:
    text = path.read_text()
    assert text == "" or text.endswith("\n"), text[-80:]
    return [json.loads(line) for line in text.splitlines()]


@pytest.mark.skipif(shutil.which("mbpoll") is None or sys.platform != "linux",
                    reason="needs mbpoll, and RLIMIT_FSIZE as a full disk")
def test_a_full_disk_stops_only_the_file_output_and_the_gateway_goes_on(tmp_path: Path
                                                                         ) -> None:
    out, port = tmp_path / "readings.jsonl", free_port()
    log = tmp_path / "stderr"
    with log.open("w") as err_file:
        # (the device answers mbpoll through the gateway: ANSWERED, rtupoll's and mbpoll's)
        proc = rtupoll_popen([sys.executable, "-m", "rtupoll", "poll", "--simulate",
                              "huiwen-aq@3", "--interval", "0.05", "--timeout", f"{ANSWERED:g}",
                              "--format", "json", "-o", str(out), "--serve", f"127.0.0.1:{port}"],
                             stdout=subprocess.DEVNULL, stderr=err_file, text=True,
                             env=NO_BYTECODE, preexec_fn=limited)

    def wait(done: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 30  # a guard against a hang, not a timing claim
        while not done():
            assert proc.poll() is None, f"exited {proc.returncode}: {log.read_text()}"
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)

    try:
        # the write that did not fit is logged once it was cut back: the file is final
        wait(lambda: "cannot write" in log.read_text())
        size = out.stat().st_size
        assert 0 < size <= LIMIT
        time.sleep(0.5)
        assert out.stat().st_size == size  # stopped: nothing more, nothing half
        read = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(port), "-1", "-o", f"{ANSWERED:g}",
                               "-a", "3", "-t", "3", "-r", "30010", "127.0.0.1"],
                              capture_output=True, text=True, timeout=60)
        assert read.returncode == 0, read.stdout + read.stderr
        with socket.create_connection(("127.0.0.1", port), timeout=2):
            pass
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
    err = log.read_text()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    said = [x for x in err.splitlines() if "cannot write" in x]
    assert len(said) == 1 and "the file output stops" in said[0], err
    records = whole_json_lines(out)
    assert records and all(r["device"] == "huiwen-aq@3" for r in records)


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def test_a_partial_last_line_is_cut_off_before_anything_is_appended(tmp_path: Path) -> None:
    out = tmp_path / "readings.jsonl"
    out.write_text('{"a": 1}\n{"b": 2}\n{"c": ')
    said = Lines()
    log = logging.getLogger("rtupoll.output")
    # whatever another test in this worker did to logging (levels, a disabled logger,
    # logging.disable), this logger's warning reaches the handler
    was = (log.level, log.disabled, logging.root.manager.disable)
    log.setLevel(logging.WARNING)
    log.disabled = False
    logging.disable(logging.NOTSET)
    log.addHandler(said)
    try:
        f = OutputFile(out)
        f.write('{"d": 4}\n')
        f.close()
    finally:
        log.removeHandler(said)
        log.setLevel(was[0])
        log.disabled = was[1]
        logging.disable(was[2])
    assert out.read_text() == '{"a": 1}\n{"b": 2}\n{"d": 4}\n'
    assert said.lines == [f"{out}: cut off a partial last line (6 bytes) an earlier run left"]


def test_poll_once_onto_a_file_an_earlier_run_cut_short(tmp_path: Path) -> None:
    out = tmp_path / "readings.csv"
    first = rtupoll("poll", "--simulate", "huiwen-aq@3", "--once", "--format", "csv",
                    "-o", str(out))
    assert first.returncode == 0, first.stderr
    lines = out.read_text().splitlines()
    out.write_bytes(out.read_bytes()[:-7])  # the last record half-written
    again = rtupoll("poll", "--simulate", "huiwen-aq@3", "--once", "--format", "csv",
                    "-o", str(out))
    assert again.returncode == 0, again.stderr
    assert "cut off a partial last line" in again.stderr
    now = out.read_text().splitlines()
    assert now[: len(lines) - 1] == lines[:-1]  # the whole lines kept, the fragment gone
    assert len(now) == 2 * len(lines) - 2  # the same records again, no second header
    assert all(line.count(",") == lines[0].count(",") for line in now)


def test_sighup_resumes_after_a_failure(tmp_path: Path) -> None:
    out = tmp_path / "readings.jsonl"
    f = OutputFile(out)
    f.failed = "No space left on device"  # as after a failed write
    f.write("lost\n")
    f.reopen()
    f.write("kept\n")
    f.close()
    assert out.read_text() == "kept\n"
