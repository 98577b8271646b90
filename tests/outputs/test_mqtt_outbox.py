"""The outbox (``outputs.mqtt_outbox``): the latest message per topic, bounded, drops
counted; what could not be sent goes back in.

Publishing from it to a real broker, across a broker that goes away, is in
``test_mqtt_cli.py``.
"""

from __future__ import annotations

from rtupoll.outputs.mqtt_outbox import Outbox


def test_outbox_keeps_the_latest_per_topic_and_is_bounded() -> None:
    box = Outbox(limit=2)
    box.put("a", "1", retain=False, qos=0)
    box.put("b", "1", retain=True, qos=0)
    box.put("a", "2", retain=False, qos=0)
    box.put("c", "1", retain=False, qos=0)  # over the limit: dropped
    assert box.dropped == 2 and len(box) == 2
    first = box.pop()
    assert first is not None and first[0] == "a" and first[1].payload == "2"
    box.restore(*first)
    assert len(box) == 2
    box.put("b", "3", retain=True, qos=0)
    second = box.pop()
    assert second is not None and second[1].payload == "3"


def test_a_message_put_back_yields_to_a_newer_one() -> None:
    box = Outbox()
    box.put("a", "1", retain=False, qos=1)
    first = box.pop()
    assert first is not None and len(box) == 0
    assert box.pop() is None and not box.ready.is_set()  # empty: nothing to wake for
    box.put("a", "2", retain=False, qos=1)  # newer, while the first was in flight
    assert first is not None
    box.restore(*first)  # the first failed: the newer one stays
    got = box.pop()
    assert got is not None and got[1].payload == "2" and len(box) == 0
