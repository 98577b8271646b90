"""The dashboard server's pure parts: the authentication check and the event hub
(rtupoll.web.server)."""

from __future__ import annotations

import asyncio
import base64

from rtupoll.config.http_settings import HttpSettings

# rtupoll.web.server and .fleet import aiohttp (0.2 s): the tests that need them import
# them, so an xdist worker that runs none of them does not pay for it at collection


def test_authorised() -> None:
    from rtupoll.web.server import COOKIE, authorised, cookie_value
    s = HttpSettings("0.0.0.0", 1, token="the-token-1", users={"tech": "correct-horse"})
    none: dict[str, str] = {}

    def basic(text: str) -> dict[str, str]:
        return {"Authorization": "Basic " + base64.b64encode(text.encode()).decode()}

    assert authorised(HttpSettings("0.0.0.0", 1), none, none, none)  # open
    assert not authorised(s, none, none, none)
    assert authorised(s, {"Authorization": "Bearer the-token-1"}, none, none)
    assert authorised(s, {"Authorization": "bearer  the-token-1"}, none, none)
    assert not authorised(s, {"Authorization": "Bearer the-token-2"}, none, none)
    assert authorised(s, none, {COOKIE: cookie_value("the-token-1")}, none)
    assert not authorised(s, none, {COOKIE: "the-token-1"}, none)  # the token is no cookie
    assert authorised(s, none, none, {"token": "the-token-1"})
    assert authorised(s, basic("tech:correct-horse"), none, none)
    assert not authorised(s, basic("tech:correct-horsE"), none, none)
    assert not authorised(s, basic("nobody:correct-horse"), none, none)
    # bytes that are not ASCII (aiohttp keeps undecodable ones as surrogates): refused,
    # never an error
    for bad in ("Bearer th\udcffe-token", "Basic \udcff\udcfe", "Basic t\u00e9st",
                "Basic " + base64.b64encode(b"tech:\xff").decode()):
        assert not authorised(s, {"Authorization": bad}, none, none), bad
    assert not authorised(s, none, {COOKIE: "\udcff"}, {"token": "\u00e9\udcff"})
    assert not authorised(s, {"Authorization": "Basic %%%"}, none, none)
    assert not authorised(s, {"Authorization": "Basic " + base64.b64encode(b"\xff").decode()},
                          none, none)


def test_the_hub_makes_each_event_once_and_gives_every_stream_the_same_bytes() -> None:
    from rtupoll.web.server import Hub
    async def run() -> None:
        hub = Hub()
        calls: list[int] = []

        def data() -> str:
            calls.append(1)
            return "2"

        hub.publish("d:a", "device", data)  # nobody listens: never made
        assert hub.pending == {}
        one = hub.join()
        two = hub.join()
        assert hub.epoch == 2  # a snapshot per client: the next device events are whole
        hub.publish("d:a", "device", "1")
        hub.publish("d:b", "device", "x")
        hub.publish("d:a", "device", data)  # the latest of a key, in its first place
        assert calls == [] and not one.wake.is_set()  # nothing until the flush
        hub.flush()  # what the timer does BATCH seconds after the first publish
        assert one.wake.is_set() and two.wake.is_set() and calls == [1]
        expected = b"event: device\ndata: 2\n\nevent: device\ndata: x\n\n"
        assert one.take() == expected and two.take() == expected
        assert not one.wake.is_set() and one.take() == b""
        hub.close()

    asyncio.run(run())


def test_a_stream_that_stops_reading_gets_a_snapshot_not_a_backlog() -> None:
    from rtupoll.web.server import BEHIND, Hub
    async def run() -> None:
        hub = Hub()
        slow, live = hub.join(), hub.join()
        chunk = "x" * 100_000
        for _ in range(BEHIND // len(chunk) + 2):
            hub.publish("d:a", "device", chunk)
            hub.flush()
            live.take()  # this one reads
        assert slow.behind and not slow.queue and slow.wake.is_set()
        assert not live.behind
        hub.publish("d:a", "device", "y")
        hub.flush()
        assert not slow.queue and live.take() == b"event: device\ndata: y\n\n"
        epoch = hub.epoch
        hub.rejoin(slow)
        assert not slow.behind and hub.epoch == epoch + 1
        hub.publish("d:a", "device", "z")
        hub.flush()
        assert slow.take() == live.take() == b"event: device\ndata: z\n\n"
        hub.close()

    asyncio.run(run())


def test_what_waits_for_all_the_slow_streams_is_bounded_together() -> None:
    """Each of 20 streams reads a little (never BEHIND): together they never hold more
    than BUDGET bytes; the furthest behind start afresh. A take is at most CHUNK bytes
    (or one event), so a slow reader's backlog stays in the hub, counted."""
    from rtupoll.web.server import BEHIND, BUDGET, CHUNK, Hub
    async def run() -> None:
        hub = Hub()
        streams = [hub.join() for _ in range(20)]
        chunk = "x" * 100_000
        most = 0
        for i in range(400):
            hub.publish("d:a", "device", chunk)
            hub.flush()
            for s in streams[:i % 20]:  # each reads now and then
                got = s.take()
                assert len(got) <= max(CHUNK, len(chunk) + 30)
            most = max(most, sum(s.size for s in hub.clients))
        assert most <= BUDGET < 20 * BEHIND
        assert any(s.behind for s in streams)  # dropped, a snapshot next
        hub.close()

    asyncio.run(run())
