"""What ``read``, ``write`` and ``set-address`` share: the device, the port, timing, consent.

Kept apart from the commands so each stays about its own job, and so the costly
imports (pymodbus via ``rtupoll.io.bus``) happen only once a command really talks to a
bus: ``--help``, ``--dry-run`` and refusals never pay for them.
"""

from __future__ import annotations

import sys
from collections.abc import Awaitable, Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from rtupoll.cli.params import Seconds
from rtupoll.config.library import load_one, note_use
from rtupoll.errors import DeviceTimeout, RefusedError, UsageError
from rtupoll.frozen import frozen
from rtupoll.model.profile import Profile
from rtupoll.numbers import parse_unit

if TYPE_CHECKING:
    from rtupoll.io.bus import Bus
    from rtupoll.io.port_settings import PortSettings

F = TypeVar("F", bound=Callable[..., object])
T = TypeVar("T")


@frozen
class Target:
    """One device: its profile (None for a bare unit address) and its unit address."""

    profile: Profile | None
    unit: int

    @property
    def name(self) -> str:
        return f"{self.profile.id}@{self.unit}" if self.profile else str(self.unit)


def load_target(text: str, profile_dirs: Iterable[Path] = (), *, bare_ok: bool = False
                ) -> Target:
    """``PROFILE@ADDRESS``, or (``bare_ok``, raw access) just ``ADDRESS``."""
    pid, sep, addr = text.rpartition("@")
    if not sep and not bare_ok:
        raise UsageError(f"{text!r} is not PROFILE@ADDRESS (e.g. huiwen-aq@1); raw registers "
                         "of a device with no profile: --raw ADDRESS")
    try:
        unit = parse_unit(addr)
    except ValueError as exc:
        raise UsageError(f"{exc} in {text!r}") from None
    if sep and not pid:
        raise UsageError(f"{text!r} names no profile before '@'")
    return Target(note_use(load_one(pid, profile_dirs)) if pid else None, unit)


def need_port(port: str | None) -> str:
    if not port:
        from rtupoll.io.port_errors import example_port

        raise UsageError(f"which port? give --port PORT (e.g. -p {example_port()}, or "
                         "tcp://HOST:PORT for a gateway), or set $RTUPOLL_PORT")
    return port


def port_settings(profile: Profile | None, port: str | None, baudrate: int | None,
                  parity: str | None, stopbits: str | None) -> PortSettings:
    """The profile's serial settings (9600 8N1 without one), each overridable; the port
    from --port or $RTUPOLL_PORT (``need_port`` says so when neither is given)."""
    from rtupoll.io.port_settings import PortSettings

    s = profile.serial if profile else None
    return PortSettings(
        port=need_port(port),
        baudrate=baudrate or (s.baudrate if s else 9600),
        parity=(parity or (s.parity if s else "N")).upper(),
        bytesize=s.bytesize if s else 8,
        stopbits=int(stopbits) if stopbits else (s.stopbits if s else 1),
        deassert_dtr=s.deassert_dtr if s else False,
        **line_settings(),
    )


def line_settings() -> dict[str, Any]:
    """``PortSettings``' echo, rs485 and idle_gap from --echo, --rs485 and --idle-gap
    (``cli.options``)."""
    from rtupoll.cli.options import given_line_options
    from rtupoll.io.port_settings import Rs485

    given = given_line_options()
    return {"echo": given.echo, "rs485": Rs485(*given.rs485) if given.rs485 else None,
            "idle_gap": given.idle_gap}


def timing_options(f: F) -> F:
    """--timeout and --retries: override the profile's per-transaction values."""
    f = click.option("--retries", type=click.IntRange(0, 10), default=None,
                     envvar="RTUPOLL_RETRIES",
                     help="Retries per request (default: the profile's). Also "
                          "$RTUPOLL_RETRIES.")(f)
    f = click.option("--timeout", type=Seconds(0.01, 30), default=None,
                     metavar="SECONDS", envvar="RTUPOLL_TIMEOUT",
                     help="Response timeout (default: the profile's). Also "
                          "$RTUPOLL_TIMEOUT.")(f)
    return f


def confirm_now(yes: bool) -> None:
    """Without a terminal, only ``--yes`` lets a change through: refused at once."""
    if not yes and not sys.stdin.isatty():
        raise RefusedError("not on a terminal, so nobody can confirm: add --yes to change "
                           "devices from a script")


def confirm(question: str, yes: bool) -> None:
    """Ask on a terminal; without one, only ``--yes`` lets a change through."""
    if yes:
        return
    confirm_now(yes)
    if not click.confirm(question, default=False, err=True):
        raise RefusedError("not confirmed: nothing was sent")


def speed_note(settings: PortSettings, profile: Profile | None, baudrate: int | None) -> str:
    """Where the speed came from, for a timeout: a wrong baud rate is the most common
    reason a device is silent in the field, so say which one was used and what to do."""
    if settings.port.startswith("tcp://"):
        return ""
    if baudrate:
        where = "as given"
    elif profile is not None:
        where = f"{profile.id}'s default"
    else:
        where = "the default without a profile"
    return (f" at {settings.baudrate} baud ({where}); if the device runs at another speed, "
            f"find it with 'rtupoll scan -p {settings.port}' or give --baudrate")


def run_on_bus(settings: PortSettings, job: Callable[[Bus], Awaitable[T]], *,
               on_timeout: str = "", blocking: bool = False) -> T:
    """Open the port, run ``job`` with the bus, close the port (whatever happens).

    ``on_timeout`` is added to a no-response error (``speed_note``). ``blocking``: a job
    that awaits only the bus's own methods runs on ``rtupoll.io.syncbus.SyncBus``, with
    no event loop (no asyncio, no pymodbus imported: a one-shot read starts faster)."""
    try:
        if blocking:
            from rtupoll.io import syncbus

            with syncbus.SyncBus(settings) as sync:
                return syncbus.run(job(sync))  # type: ignore[arg-type]  # a BusLike, not a Bus

        from rtupoll.io.bus import Bus

        async def main() -> T:
            async with Bus(settings) as bus:
                return await job(bus)

        from rtupoll import aio

        return aio.run(main())
    except DeviceTimeout as exc:
        if not on_timeout:
            raise
        raise type(exc)(f"{exc}{on_timeout}") from None
