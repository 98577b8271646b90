"""``rtupoll poll``'s ``--serve*`` options, and the ``ServeConfig`` they make."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import click
from click.core import ParameterSource

from rtupoll.cli.params import Seconds
from rtupoll.config.gateway_settings import (
    DEFAULT_CLIENT_QUEUE,
    DEFAULT_MAX_CLIENTS,
    DEFAULT_MAX_PER_ADDRESS,
    DEFAULT_QUEUE,
    DEFAULT_TIMEOUT,
    ServeConfig,
    serve_config,
)
from rtupoll.errors import UsageError

F = TypeVar("F", bound=Callable[..., Any])


def serve_options(f: F) -> F:
    """The options; ``poll`` takes them as ``**serve`` and calls ``from_options``."""
    for option in reversed((
        click.option("--serve", "serve", default=None, metavar="[tcp://|rtu+tcp://][HOST:]PORT",
                     help="Serve Modbus TCP (or RTU over TCP) to other masters, sharing this "
                          "bus (HOST defaults to 127.0.0.1; see docs/gateway.md)."),
        click.option("--serve-allow", "serve_allow", multiple=True, metavar="CIDR",
                     help="--serve: client networks allowed (repeatable; default: any)."),
        click.option("--serve-read-only", "serve_read_only", is_flag=True,
                     help="--serve: pass only reads of coils and registers (FC 1-4); "
                          "refuse everything else (exception 01)."),
        click.option("--serve-cache", "serve_cache", type=Seconds(0, 3600),
                     default=0.0, metavar="SECONDS",
                     help="--serve: answer reads from data polled at most this long ago."),
        click.option("--serve-broadcast", "serve_broadcast", is_flag=True,
                     help="--serve: pass broadcast writes (unit 0; FC 5, 6, 15, 16, 22) to "
                          "the line."),
        click.option("--serve-setup-writes", "serve_setup_writes", multiple=True,
                     type=click.IntRange(1, 247), metavar="UNIT",
                     help="--serve: let clients write this unit's address and baud-rate "
                          "registers and send it state-changing diagnostics (repeatable)."),
        click.option("--serve-queue", "serve_queue", type=click.IntRange(1, 1000),
                     default=DEFAULT_QUEUE, show_default=True,
                     help="--serve: requests beyond each client's first that may wait for "
                          "the line (all clients together); more get 0x0A."),
        click.option("--serve-client-queue", "serve_client_queue", type=click.IntRange(1, 100),
                     default=DEFAULT_CLIENT_QUEUE, show_default=True,
                     help="--serve: one client's requests that may wait; beyond, rtupoll "
                          "stops reading from it until its replies are read."),
        click.option("--serve-max-clients", "serve_max_clients",
                     type=click.IntRange(1, 10000), default=DEFAULT_MAX_CLIENTS,
                     show_default=True,
                     help="--serve: connections at once; more are closed as they come."),
        click.option("--serve-max-per-address", "serve_max_per_address",
                     type=click.IntRange(1, 10000), default=DEFAULT_MAX_PER_ADDRESS,
                     show_default=True,
                     help="--serve: connections at once from one client address."),
        click.option("--serve-timeout", "serve_timeout", type=Seconds(0.01, 30),
                     default=DEFAULT_TIMEOUT, show_default=True,
                     help="--serve: response timeout for units rtupoll does not poll."),
    )):
        f = option(f)
    return f


def from_options(opts: Mapping[str, Any]) -> ServeConfig | None:
    """The ``ServeConfig`` of ``--serve``; None without it (other --serve-* then refused)."""
    listen = opts.get("serve")
    if listen is None:
        source = click.get_current_context().get_parameter_source
        given = [k for k in opts if k != "serve" and source(k) is not ParameterSource.DEFAULT]
        if given:
            raise UsageError(f"--{given[0].replace('_', '-')} is an option of --serve")
        return None
    return serve_config(listen, allow=opts["serve_allow"], read_only=opts["serve_read_only"],
                        cache=opts["serve_cache"], broadcast=opts["serve_broadcast"],
                        setup_writes=opts["serve_setup_writes"], queue=opts["serve_queue"],
                        timeout=opts["serve_timeout"], client_queue=opts["serve_client_queue"],
                        max_clients=opts["serve_max_clients"],
                        max_per_address=opts["serve_max_per_address"])
