"""The event loop every command runs on: asyncio's selector loop, on every platform.

Linux and macOS have it by default. Windows's default, the proactor loop, has no
``add_reader``/``add_writer``, which rtupoll's MQTT client (``outputs/mqtt_client.py``)
and aiomqtt wait on their sockets with; so on Windows too the commands run on
``asyncio.SelectorEventLoop`` (sockets only, there: a serial port is polled by
pymodbus's transport, ``SerialTransport.force_poll``, on either loop). Its Ctrl-C is a
Python handler (``cli.stop_event``): the loop has no ``add_signal_handler`` there.
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")


def run(main: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run(main)`` on a selector loop."""
    with asyncio.Runner(loop_factory=asyncio.SelectorEventLoop) as runner:
        return runner.run(main)


def new_loop() -> asyncio.AbstractEventLoop:
    """``asyncio.new_event_loop()``, a selector loop."""
    return asyncio.SelectorEventLoop()
