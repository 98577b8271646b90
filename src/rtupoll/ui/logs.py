"""What ``rtupoll poll`` tells an operator's log: state changes, not repetitions.

``setup`` sends the ``rtupoll`` loggers to stderr as human lines (``text``) or one
JSON object per line (``json``, for journald or Loki), with the event's fields
(``event``, ``bus``, ``device``, ``state``, ``error``) as keys. ``StateLog`` is a
service (``rtupoll.jobs.services``) that watches every device cycle and logs a
line only when something changes: a device that times out every scan is logged
once when it stops answering and once when it is back, with how long it was gone;
a port that goes away is logged once, and again when it returns.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

from rtupoll.jobs.services import Service
from rtupoll.model.record import iso_time
from rtupoll.numbers import count
from rtupoll.rtu.line import ECHO_FOUND
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.jobs.scheduler import DevicePoller, Scheduler
    from rtupoll.jobs.stats import Reading

log = logging.getLogger("rtupoll")
_EXTRA = ("event", "bus", "device", "profile", "address", "state", "status", "error", "file",
          "ok", "timeouts", "late", "garbled", "exceptions", "attempts", "timed_out_attempts",
          "garbled_attempts", "retried", "idle_gap")


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, message and the event's own keys."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {"time": iso_time(record.created),
                               "level": record.levelname.lower(),
                               "message": record.getMessage()}
        for k in _EXTRA:
            v = getattr(record, k, None)
            if v is not None:
                out[k] = v
        if record.exc_info:
            out["traceback"] = self.formatException(record.exc_info)
        return to_json(out)  # NaN and infinities as null


class TextFormatter(logging.Formatter):
    """``TIME LEVEL message`` (journald adds its own time, but a file needs one)."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{iso_time(record.created)} {record.levelname.lower():7} {record.getMessage()}"


class _Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Whatever ``sys.stderr`` is when a line is written (a test runner swaps it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, value: TextIO) -> None:
        pass


def setup(fmt: str = "text", stream: TextIO | None = None, level: int = logging.INFO
          ) -> logging.Handler:
    """Route the ``rtupoll`` loggers to ``stream`` (default: stderr) in ``fmt``, replacing
    what an earlier call set up; returns the handler."""
    handler: logging.Handler = logging.StreamHandler(stream) if stream is not None \
        else _Stderr()
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    for h in list(log.handlers):
        if getattr(h, "_rtupoll", False):
            log.removeHandler(h)
    setattr(handler, "_rtupoll", True)  # noqa: B010 (marks the handler this module added)
    log.addHandler(handler)
    log.setLevel(level)
    return handler


@dataclass
class _Seen:
    condition: str  # "online", or the problem's kind ("timeout", "exception 02", ...)
    since: float  # wall time the condition began
    failed_cycles: int = 0


class StateLog(Service):
    """A service that logs each device's and each port's changes of state, once each."""

    def __init__(self, wall: Callable[[], float] = time.time) -> None:
        self._wall = wall
        self._seen: dict[str, _Seen] = {}
        self._ports: dict[str, str] = {}  # bus name -> the port error while it is gone
        self._late: set[str] = set()  # devices whose late replies were logged
        self._echoed: set[str] = set()  # buses whose adapter's echo was logged
        self._bus_of: dict[str, str] = {}
        self._scheduler: Scheduler | None = None

    async def start(self, scheduler: Scheduler) -> None:
        self._scheduler = scheduler
        self._index()
        for bp in scheduler.buses:
            log.info("polling %s (%s, %s): %s", bp.config.name, bp.config.port,
                     bp.config.serial_text, count(len(bp.devices), "device"),
                     extra={"event": "bus", "bus": bp.config.name})

    def _index(self) -> None:
        if self._scheduler is not None:
            self._bus_of = {d.config.name: bp.config.name for bp in self._scheduler.buses
                            for d in bp.devices}

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        name = dev.config.name
        if name not in self._bus_of:
            self._index()
        bus = self._bus_of.get(name, "")
        now = self._wall()
        if bus not in self._echoed and self._scheduler is not None and any(
                bp.transport.echo_found for bp in self._scheduler.buses
                if bp.config.name == bus):  # once per bus (rtu.line: Line.adopt_echo)
            self._echoed.add(bus)
            log.warning("%s: %s", bus, ECHO_FOUND, extra={"event": "echo", "bus": bus})
        if readings and all(r.status == "port" for r in readings):
            if bus not in self._ports:
                self._ports[bus] = readings[0].error
                log.error("%s: port lost: %s (retrying)", bus, readings[0].error,
                          extra={"event": "port", "bus": bus, "state": "lost",
                                 "error": readings[0].error})
            return
        if bus in self._ports:
            gone = self._ports.pop(bus)
            log.info("%s: port back (was: %s)", bus, gone,
                     extra={"event": "port", "bus": bus, "state": "open"})
        condition, first = _condition(dev, readings)
        seen = self._seen.get(name)
        who = name if name == dev.config.spec else f"{name} ({dev.config.spec})"
        st = dev.stats
        extra = {"event": "device", "bus": bus, "device": name,
                 "profile": dev.config.profile.id, "address": dev.config.address,
                 "state": st.state.value, "ok": st.ok, "timeouts": st.timeouts,
                 "late": st.late, "garbled": st.garbled, "exceptions": st.exception_count,
                 "attempts": st.attempts, "timed_out_attempts": st.timed_out,
                 "garbled_attempts": st.garbled_attempts, "retried": st.retried,
                 "idle_gap": st.idle_gap}
        if st.late and name not in self._late:  # the first late reply: once per device
            self._late.add(name)
            log.warning("%s on %s: a reply came after its timeout (counted late, never "
                        "decoded); the device may need a longer timeout", who, bus,
                        extra={**extra, "event": "late", "status": "late"})
        if seen is None:
            self._seen[name] = _Seen(condition, now, 0 if condition == "online" else 1)
            if condition != "online" and first is not None:
                log.warning("%s on %s: %s: %s", who, bus, first.status, first.error,
                            extra={**extra, "status": first.status, "error": first.error})
            return
        if condition != "online":
            seen.failed_cycles += 1
        if condition == seen.condition:
            return
        self._seen[name] = _Seen(condition, now, 0 if condition == "online" else 1)
        if condition == "online":
            log.info("%s on %s: answering again (%s for %.0f s, %d cycles)", who, bus,
                     seen.condition, now - seen.since, seen.failed_cycles, extra=extra)
        elif first is not None:
            log.warning("%s on %s: %s: %s", who, bus, first.status, first.error,
                        extra={**extra, "status": first.status, "error": first.error})

    async def stop(self) -> None:
        return None


def _condition(dev: DevicePoller, readings: list[Reading]) -> tuple[str, Reading | None]:
    """``online`` when the device answers with everything, else the first problem's kind
    (a device online with one field's exception is a condition of its own)."""
    problems = [r for r in readings if not r.ok and r.status not in ("absent", "skipped")]
    if not problems:
        return "online", None
    first = problems[0]
    kind = first.status.value
    if kind == "exception":
        kind = "exception " + first.error.split("exception ", 1)[-1][:2]
    return kind, first
