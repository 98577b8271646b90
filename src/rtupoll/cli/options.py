"""Options shared by several commands, defined once."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import click

F = TypeVar("F", bound=Callable[..., object])

profiles_option = click.option(
    "--profiles", "profile_dirs", multiple=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Extra profile directory (repeatable; also $RTUPOLL_PROFILES). Searched before "
         "the bundled profiles.")


def format_option(*choices: str) -> Callable[[F], F]:
    return click.option("--format", "fmt", type=click.Choice(list(choices)),
                        default=choices[0], show_default=True, help="Output format.")


def port_options(f: F) -> F:
    """--port, --baudrate, --parity, --stopbits: serial settings (default: the profile's)."""
    f = click.option("--stopbits", type=click.Choice(["1", "2"]), default=None,
                     help="Stop bits (default: the profile's).")(f)
    f = click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False),
                     default=None, help="Parity (default: the profile's).")(f)
    f = click.option("--baudrate", "-b", type=click.IntRange(300, 4_000_000), default=None,
                     help="Baud rate (default: the profile's).")(f)
    f = click.option("--port", "-p", required=True, envvar="RTUPOLL_PORT",
                     help="Serial port (/dev/ttyUSB0), or tcp://HOST:PORT for an RTU-over-TCP "
                          "gateway. Also $RTUPOLL_PORT.")(f)
    return f


def service_options(f: F) -> F:
    """--metrics, --log-format: ``poll`` as a service (docs/service.md)."""
    f = click.option("--log-format", "log_format", type=click.Choice(["text", "json"]),
                     default=None,
                     help="Log device and port state changes on stderr: text, or one JSON "
                          "object per line (journald, Loki). Default: text when stderr is a "
                          "terminal or the journal, else errors only.")(f)
    f = click.option("--metrics", "metrics", metavar="HOST:PORT", default=None,
                     help="Serve Prometheus metrics at http://HOST:PORT/metrics; ':PORT' "
                          "listens on 127.0.0.1 only, 0.0.0.0:PORT or [::]:PORT on every "
                          "interface (also 'metrics:' in the site file).")(f)
    return f
