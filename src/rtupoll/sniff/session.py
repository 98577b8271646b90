"""One listening session: chunks in, transactions and records out, the capture kept.

The same path for a live port and for a capture read back (``--read``): the chunks and
their arrival times are all that is fed, so a capture decodes exactly as it did live.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rtupoll.rtu.stream import TIMEOUT, Stream, Transaction
from rtupoll.rtu.timing import Framing
from rtupoll.sniff.capfile import CaptureWriter
from rtupoll.sniff.model import BusView

Sink = Callable[[Transaction, list[dict[str, Any]]], None]


class Session:
    def __init__(self, framing: Framing, view: BusView, sink: Sink, *,
                 timeout: float = TIMEOUT, capture: CaptureWriter | None = None) -> None:
        self.stream = Stream(framing, timeout=timeout)
        self.view, self.sink, self.capture = view, sink, capture
        self.bytes = 0

    def feed(self, data: bytes, t: float) -> None:
        """A chunk as it arrived (``b""``: time passed in silence). The time is taken at
        the capture's resolution (whole microseconds), so that what is decoded live and
        what is decoded from the capture later see the very same times."""
        t = round(t * 1_000_000) / 1_000_000
        if data:
            self.bytes += len(data)
            if self.capture is not None:
                self.capture.write(data, t)
        self._emit(self.stream.feed(data, t))

    def run(self, chunks: Iterable[tuple[bytes, float]]) -> None:
        for data, t in chunks:
            self.feed(data, t)

    def close(self) -> None:
        self._emit(self.stream.close())
        if self.capture is not None:
            self.capture.close()

    def _emit(self, txs: list[Transaction]) -> None:
        for tx in txs:
            self.sink(tx, self.view.add(tx))
