"""The outbox: what waits for the broker, what was dropped, what went out.

``on_readings`` only puts a message here, so the broker never holds up polling. The
outbox keeps the latest message per topic (a device's intermediate states are dropped
while the broker is slow or away, its latest kept), bounded by ``MAX_PENDING`` topics;
``drain`` publishes from it for one session, and a message that could not be sent
goes back in for the next.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import aiomqtt

__all__ = ["MAX_INFLIGHT", "MAX_PENDING", "Message", "Outbox"]

MAX_PENDING = 20_000  # topics the outbox holds at most while the broker is away
MAX_INFLIGHT = 20  # QoS 1/2 messages awaiting their acknowledgement (paho's default)


@dataclass(frozen=True)
class Message:
    payload: str
    retain: bool
    qos: int


class Outbox:
    """Messages waiting for the broker: the latest per topic, oldest topic first."""

    def __init__(self, limit: int = MAX_PENDING) -> None:
        self._pending: dict[str, Message] = {}
        self.limit = limit
        self.dropped = 0  # messages replaced by a newer one on the same topic, or over limit
        self.published = 0  # messages the broker took
        self.ready = asyncio.Event()  # something is waiting
        self.flushed = asyncio.Event()  # nothing is waiting, nothing awaits its ack

    def put(self, topic: str, payload: str, *, retain: bool, qos: int) -> None:
        if topic in self._pending:
            self.dropped += 1
        elif len(self._pending) >= self.limit:
            self.dropped += 1
            return
        self._pending[topic] = Message(payload, retain, qos)
        self.ready.set()

    def pop(self) -> tuple[str, Message] | None:
        if not self._pending:
            self.ready.clear()
            return None
        topic = next(iter(self._pending))
        return topic, self._pending.pop(topic)

    def restore(self, topic: str, msg: Message) -> None:
        """Put back a message that could not be sent (unless a newer one came meanwhile)."""
        if topic not in self._pending:
            self._pending[topic] = msg
            self.ready.set()

    def __len__(self) -> int:
        return len(self._pending)

    async def drain(self, client: aiomqtt.Client) -> None:
        """Publish from the outbox until the session breaks (its error raised). QoS 0
        goes out one message after the other; QoS 1 and 2 keep up to ``MAX_INFLIGHT``
        messages awaiting their acknowledgement, so a distant broker's round trip does
        not set the pace."""
        inflight: set[asyncio.Task[None]] = set()
        errors: list[BaseException] = []
        window = asyncio.Semaphore(MAX_INFLIGHT)

        def finished(task: asyncio.Task[None]) -> None:
            inflight.discard(task)
            if not task.cancelled() and task.exception() is not None:
                errors.append(task.exception())  # type: ignore[arg-type]

        try:
            while True:
                if errors:
                    raise errors[0]
                item = self.pop()
                if item is None:
                    if inflight:
                        await asyncio.wait(set(inflight))
                        continue
                    self.flushed.set()
                    await self.ready.wait()
                    continue
                topic, msg = item
                if msg.qos == 0:
                    await self._send(client, topic, msg)
                    continue
                await window.acquire()
                task = asyncio.create_task(self._send(client, topic, msg, window))
                inflight.add(task)
                task.add_done_callback(finished)
        finally:
            for task in list(inflight):
                task.cancel()
            await asyncio.gather(*inflight, return_exceptions=True)

    async def _send(self, client: aiomqtt.Client, topic: str, msg: Message,
                    window: asyncio.Semaphore | None = None) -> None:
        try:
            await client.publish(topic, msg.payload, qos=msg.qos, retain=msg.retain)
        except BaseException:
            self.restore(topic, msg)  # sent again after reconnecting
            raise
        else:
            self.published += 1
        finally:
            if window is not None:
                window.release()
