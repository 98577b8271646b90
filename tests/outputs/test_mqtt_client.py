"""The MQTT connection's socket registrations (``outputs.mqtt_client.SafeClient``).

paho hands aiomqtt its socket to watch; aiomqtt 2.x schedules the loop's
``add_reader``/``add_writer`` for the descriptor number taken at once. When the broker
goes away, paho closes the socket before the loop runs the call: the loop then logs
"Exception in callback ... OSError: [Errno 9] Bad file descriptor" (what Python 3.13
users saw; 3.11 logs it too), or, when a new socket got the same number meanwhile,
watches it for the dead client. These tests play that order of events with real
sockets and the real client class, on whatever Python runs them (aiomqtt's own class
fails every one of them). paho's side is played on a real paho client: its socket, and
whether it has something to write.
"""

from __future__ import annotations

import asyncio
import socket
from typing import Any

import pytest

from rtupoll.outputs.mqtt_client import client_class


def watched(loop: asyncio.AbstractEventLoop, fd: int) -> tuple[bool, bool]:
    """(reader, writer) registered for ``fd`` in the loop's selector."""
    selector = loop._selector  # type: ignore[attr-defined]
    key = selector.get_map().get(fd)
    if key is None:
        return False, False
    reader, writer = key.data
    return reader is not None, writer is not None


async def settle() -> None:
    for _ in range(3):
        await asyncio.sleep(0)


def errors_of(loop: asyncio.AbstractEventLoop) -> list[Any]:
    seen: list[Any] = []
    loop.set_exception_handler(lambda _loop, ctx: seen.append(ctx))
    return seen


@pytest.mark.parametrize("hook", ["_on_socket_open", "_on_socket_register_write"])
@pytest.mark.parametrize("reused", [False, True])
def test_a_socket_closed_before_the_loop_registers_it_is_left_alone(hook: str,
                                                                    reused: bool) -> None:
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        errors = errors_of(loop)
        client = client_class()("127.0.0.1", 1)
        paho = client._client
        sock, _peer = socket.socketpair()
        fd = sock.fileno()
        paho._sock = sock
        paho.want_write = lambda: True  # a CONNECT or a PUBLISH waits
        getattr(client, hook)(paho, None, sock)  # what paho calls, the broker still there
        paho._sock = None  # ... then the broker goes away: paho closes the socket
        sock.close()
        newer = socket.socketpair() if reused else None  # the reconnection's socket
        if newer is not None:
            assert newer[0].fileno() == fd  # the number is taken again at once
        await settle()
        assert errors == []  # nothing for the loop to log
        assert watched(loop, fd) == (False, False)  # nor a dead client on a new socket
        if client._misc_task is not None:
            client._misc_task.cancel()
        for s in newer or ():
            s.close()
        _peer.close()

    asyncio.run(scenario())


def test_a_live_socket_is_watched_as_before() -> None:
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        errors = errors_of(loop)
        client = client_class()("127.0.0.1", 1)
        paho = client._client
        sock, peer = socket.socketpair()
        paho._sock = sock
        pending = [True]
        paho.want_write = lambda: pending[0]  # what paho has to write, played
        written: list[int] = []
        paho.loop_write = lambda: written.append(1)  # paho's writer, observed
        client._on_socket_open(paho, None, sock)
        await settle()
        assert watched(loop, sock.fileno()) == (True, False)
        assert client._misc_task is not None and not client._misc_task.done()  # keepalive
        client._on_socket_register_write(paho, None, sock)
        await settle()
        assert watched(loop, sock.fileno()) == (True, True)
        await settle()  # a socketpair is writable at once: the writer ran
        assert written
        client._on_socket_unregister_write(paho, None, sock)
        assert watched(loop, sock.fileno()) == (True, False)
        # paho wrote it all before the loop ran the registration: it stays unregistered
        client._on_socket_register_write(paho, None, sock)
        pending[0] = False
        await settle()
        assert watched(loop, sock.fileno()) == (True, False)
        client._on_socket_close(paho, None, sock)
        assert watched(loop, sock.fileno()) == (False, False)
        await settle()
        assert client._misc_task.done()
        assert errors == []
        sock.close()
        peer.close()

    asyncio.run(scenario())
