"""The MQTT line under the live table (``ui.mqtt_footer``)."""

from __future__ import annotations

from rtupoll.ui.mqtt_footer import line


def test_the_line_says_where_how_and_how_much() -> None:
    where = "mqtt://broker.lan:1883/plant"
    common = {"error": "", "published": 7, "waiting": 2}
    assert line(where, connected=False, lost_for=None, **common).plain == \
        "mqtt mqtt://broker.lan:1883/plant · connecting · 7 published · 2 waiting"
    assert line(where, connected=True, lost_for=None, **common).plain == \
        "mqtt mqtt://broker.lan:1883/plant · connected · 7 published · 2 waiting"
    lost = line(where, connected=False, lost_for=41.6, error="connection refused",
                published=7, waiting=2)
    assert lost.plain == ("mqtt mqtt://broker.lan:1883/plant · broker lost 42 s ago "
                          "(connection refused), reconnecting · 7 published · 2 waiting")
    assert any(span.style == "yellow" for span in lost.spans)  # the news stands out
