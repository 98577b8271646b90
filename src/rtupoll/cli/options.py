"""Options shared by several commands, defined once."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import click

from rtupoll.frozen import frozen
from rtupoll.model.profile import idle_gap_error

F = TypeVar("F", bound=Callable[..., object])

profiles_option = click.option(
    "--profiles", "profile_dirs", multiple=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Extra profile directory (repeatable; also $RTUPOLL_PROFILES). Searched before "
         "the bundled profiles.")


def format_option(*choices: str) -> Callable[[F], F]:
    return click.option("--format", "fmt", type=click.Choice(list(choices)),
                        default=choices[0], show_default=True, help="Output format.")


@frozen
class LineOptions:
    """--echo, --rs485, --idle-gap: how the adapter meets the line (``line_options``)."""

    echo: bool = False
    rs485: tuple[float, float] | None = None  # (before, after) in seconds; None: off
    idle_gap: float = 0.0  # seconds of silence every device gets before a request


_LINE_KEY = "rtupoll.line_options"
_TRAFFIC_KEY = "rtupoll.traffic"


def line_options(f: F) -> F:
    """--echo, --rs485, --rs485-delays, --idle-gap: adapters that echo, transceivers
    whose direction is on RTS, devices that need a longer silence. Kept in the click
    context (``given_line_options``), so every command that opens a port takes them
    without a parameter of its own."""
    def keep(ctx: click.Context, param: click.Parameter, value: object) -> None:
        if value in (None, False):
            return
        now = ctx.meta.get(_LINE_KEY, LineOptions())
        if param.name == "echo":
            ctx.meta[_LINE_KEY] = dataclasses.replace(now, echo=True)
        elif param.name == "rs485":
            ctx.meta[_LINE_KEY] = dataclasses.replace(now, rs485=now.rs485 or (0.0, 0.0))
        elif param.name == "idle_gap":
            gap = float(str(value)) if _is_number(str(value)) else -1.0
            why = idle_gap_error(gap)
            if why:
                raise click.BadParameter(f"{value!r}: seconds of silence, e.g. 0.05 "
                                         f"({'not a number' if gap == -1.0 else why})",
                                         ctx=ctx, param=param)
            ctx.meta[_LINE_KEY] = dataclasses.replace(now, idle_gap=gap)
        else:
            text = str(value)
            try:
                parts = [float(x) / 1000 for x in text.split(",")]
            except ValueError:
                parts = []
            if not 1 <= len(parts) <= 2 or any(not 0 <= x <= 1 for x in parts):
                raise click.BadParameter(f"{text!r}: give BEFORE_MS[,AFTER_MS], each "
                                         "0..1000 (e.g. 0,0.5)", ctx=ctx, param=param)
            ctx.meta[_LINE_KEY] = dataclasses.replace(
                now, rs485=(parts[0], parts[-1] if len(parts) > 1 else 0.0))

    f = click.option("--idle-gap", metavar="SECONDS", default=None, expose_value=False,
                     callback=keep,
                     help="Silence the line must have before each request, for devices that "
                          "need a pause between commands (at least; a profile's "
                          "limits.idle_gap may ask for more).")(f)
    f = click.option("--rs485-delays", metavar="BEFORE_MS[,AFTER_MS]", default=None,
                     expose_value=False, callback=keep,
                     help="--rs485: milliseconds between raising RTS and the first bit, "
                          "and between the last bit and dropping it (default 0,0).")(f)
    f = click.option("--rs485", is_flag=True, default=False, expose_value=False,
                     callback=keep,
                     help="Drive the RS-485 transceiver's direction (DE/RE on RTS): the "
                          "kernel's RS-485 mode where the driver has it, else RTS raised "
                          "around each frame.")(f)
    f = click.option("--echo", is_flag=True, default=False, expose_value=False,
                     callback=keep,
                     help="The adapter echoes every request back (a 2-wire adapter whose "
                          "receiver is always on): consume the echo, which must match.")(f)
    return traffic_options(f)


def traffic_options(f: F) -> F:
    """--traffic and --capture: the command's own frames, as log lines and a pcapng file
    (``rtupoll.sniff.traffic``); nothing is loaded or called without them."""
    def keep(ctx: click.Context, param: click.Parameter, value: object) -> None:
        if value is None or value is False:
            return
        from rtupoll.io import taps
        from rtupoll.sniff.traffic import Traffic

        root = ctx.find_root()
        traffic = root.meta.get(_TRAFFIC_KEY)
        if not isinstance(traffic, Traffic):
            traffic = root.meta[_TRAFFIC_KEY] = Traffic(None, None)
            taps.listen(traffic)
            root.call_on_close(traffic.close)
            root.call_on_close(lambda: taps.listen(None))
        if param.name == "traffic":
            traffic.fmt = traffic.fmt or "text"
        elif param.name == "traffic_format":
            traffic.fmt = str(value)
        else:
            traffic.capture_path = Path(str(value))

    f = click.option("--capture", "capture", metavar="FILE", default=None,
                     type=click.Path(dir_okay=False), expose_value=False, callback=keep,
                     help="Write the frames sent and received to FILE (pcapng, as 'sniff "
                          "--capture': Wireshark and 'sniff --read' read it).")(f)
    f = click.option("--traffic-format", type=click.Choice(["text", "json"]), default=None,
                     expose_value=False, callback=keep,
                     help="--traffic as text lines (default) or one JSON object a frame.")(f)
    f = click.option("--traffic", is_flag=True, default=None, expose_value=False,
                     callback=keep,
                     help="Show each frame sent and received on stderr: its time, "
                          "direction, port, bytes in hex and decoding.")(f)
    return f


def _is_number(text: str) -> bool:
    try:
        return float(text) == float(text)  # not NaN
    except ValueError:
        return False


def given_line_options() -> LineOptions:
    """--echo and --rs485 as given to the running command (off outside one)."""
    ctx = click.get_current_context(silent=True)
    found = ctx.find_root().meta.get(_LINE_KEY) if ctx is not None else None
    return found if isinstance(found, LineOptions) else LineOptions()


def port_options(f: F) -> F:
    """--port, --baudrate, --parity, --stopbits (default: the profile's), --echo, --rs485."""
    f = line_options(f)
    f = click.option("--stopbits", type=click.Choice(["1", "2"]), default=None,
                     help="Stop bits (default: the profile's).")(f)
    f = click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False),
                     default=None, help="Parity (default: the profile's).")(f)
    f = click.option("--baudrate", "-b", type=click.IntRange(300, 4_000_000), default=None,
                     help="Baud rate (default: the profile's).")(f)
    f = click.option("--port", "-p", envvar="RTUPOLL_PORT",
                     help="Serial port (/dev/ttyUSB0, COM3), a network serial port "
                          "(rfc2217://HOST:PORT, socket://HOST:PORT), or tcp://HOST:PORT for "
                          "an RTU-over-TCP gateway. Also $RTUPOLL_PORT.")(f)
    return f


def service_options(f: F) -> F:
    """--metrics, --log-format: ``poll`` as a service (docs/service.md)."""
    f = click.option("--log-format", "log_format", type=click.Choice(["text", "json"]),
                     default=None,
                     help="Log device and port state changes on stderr: text, or one JSON "
                          "object per line (journald, Loki). Default: text when stderr is a "
                          "terminal or the journal, else errors only.")(f)
    f = click.option("--metrics", "metrics", metavar="[HOST:]PORT", default=None,
                     help="Serve Prometheus metrics at http://HOST:PORT/metrics; a port "
                          "alone listens on 127.0.0.1 only, 0.0.0.0:PORT or [::]:PORT on "
                          "every interface (also 'metrics:' in the site file).")(f)
    return f
