"""The sniffer and ``scale_by``: a CT-operated meter another master polls shows primary
values once the sniffer has seen its ratio read, and no value (``unscaled``) before."""

from __future__ import annotations

from rtupoll.model.interpret import field_words
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.rtu.stream import Stream, Transaction
from rtupoll.sim.scenario import profile
from rtupoll.sniff.model import BusView, Known

F = Framing(9600)
METER = Known("grid", profile("chint-dtsu666"), 1)
T0 = 1_700_000_000.0


def transactions(*exchanges: tuple[bytes, bytes]) -> list[Transaction]:
    s, out, t = Stream(F, timeout=0.5), [], T0
    for request, reply in exchanges:
        end = t + F.wire_time(len(request))
        out += s.feed(request, end)
        out += s.feed(reply, end + 0.02 + F.wire_time(len(reply)))
        t += 1.0
    return out + s.close()


def test_a_current_is_unscaled_until_the_ratio_is_seen_then_primary() -> None:
    p = METER.profile
    cur, ratios = p.field("current_l1"), p.field("current_ratio")
    amps = ReadRequest(1, 3, cur.address, 2).frame(), \
        ReadReply(1, 3, tuple(list(field_words(cur, 0.035)))).frame()
    ratio = ReadRequest(1, 3, ratios.address, 2).frame(), ReadReply(1, 3, (200, 10)).frame()
    view = BusView([METER])
    recs = [r for tx in transactions(amps, ratio, amps) for r in view.add(tx)]
    by = [(r["field"], r["status"], r["value"]) for r in recs]
    assert by == [("current_l1", "unscaled", None), ("current_ratio", "ok", 200),
                  ("voltage_ratio", "ok", 1.0), ("current_l1", "ok", 7.0)]
    assert recs[0]["error"] == "current_ratio (scale_by) was not read"
    assert view.units[1].latest["current_l1"][1].value == 7.0
