"""Where a service of rtupoll listens: one rule for ``--http``, ``--metrics`` and
``--serve`` (and the site file's ``http:``, ``metrics:`` and ``serve:``).

``HOST:PORT``, ``[v6]:PORT``, and ``:PORT`` or ``PORT`` alone: loopback only, so other
machines reach a service only when a host says so (``0.0.0.0:PORT``, ``[::]:PORT``).
"""

from __future__ import annotations

from rtupoll.errors import UsageError

LOOPBACK = "127.0.0.1"


def host_port(text: str, *, port_zero: bool = True) -> tuple[str, int] | None:
    """(host, port) of ``text``, or None when it is no listen address or its port is out
    of range (0, "any free port", only with ``port_zero``)."""
    host, _, number = text.strip().rpartition(":")
    if not number.isdigit() or not (0 if port_zero else 1) <= int(number) <= 65535:
        return None
    return host.strip("[]") or LOOPBACK, int(number)


def listen_address(text: str, option: str, example: str, *, port_zero: bool = True
                   ) -> tuple[str, int]:
    """(host, port) of ``text``, or one line naming ``option`` and an ``example``."""
    got = host_port(text, port_zero=port_zero)
    if got is None:
        raise UsageError(f"{option} {text!r}: expected [HOST:]PORT, e.g. {example}")
    return got
