"""The sniffer's view of the bus, from transactions alone (no port, no clock)."""

from __future__ import annotations

from rtupoll.config.library import load_library
from rtupoll.model.record import POLL_KEYS
from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ExceptionReply, ReadReply, ReadRequest, WriteSingle
from rtupoll.rtu.stream import Stream, Transaction
from rtupoll.sim.scenario import profile
from rtupoll.sniff.lines import frame_line
from rtupoll.sniff.model import BusView, Known
from rtupoll.sniff.render import render

F = Framing(9600)
HUIWEN = Known("air", profile("huiwen-aq"), 3)
T0 = 1_700_000_000.0


def transactions(*exchanges: tuple[bytes, bytes | None]) -> list[Transaction]:
    """Each request and its reply (None: none) 20 ms later, one exchange per 0.1 s."""
    s, out, t = Stream(F, timeout=0.5), [], T0
    for request, reply in exchanges:
        end = t + F.wire_time(len(request))
        out += s.feed(request, end)
        if reply is not None:
            out += s.feed(reply, end + 0.02 + F.wire_time(len(reply)))
        t += 1.0
    return out + s.close()


def test_a_read_of_a_known_device_gives_poll_records() -> None:
    view = BusView([HUIWEN])
    [tx] = transactions((ReadRequest(3, 4, 30006, 4).frame(),
                         ReadReply(3, 4, (25, 50, 250, 800)).frame()))
    recs = view.add(tx)
    assert [(r["field"], r["value"], r["unit"]) for r in recs] == [
        ("pm25", 25, "µg/m³"), ("tvoc", 0.05, "ppm"), ("hcho", 0.25, "ppm"), ("co2", 800, "ppm")]
    assert all(tuple(r) == POLL_KEYS for r in recs)
    assert recs[0]["device"] == "air" and recs[0]["status"] == "ok"
    assert recs[0]["time"].endswith("Z")
    u = view.units[3]
    assert (u.requests, u.ok) == (1, 1)
    assert u.p50() is not None and 0.015 < u.p50() < 0.025  # type: ignore[operator]


def test_failures_give_records_without_values() -> None:
    view = BusView([HUIWEN])
    co2 = ReadRequest(3, 4, 30009, 1).frame()
    txs = transactions((co2, None), (co2, ExceptionReply(3, 4, 4).frame()),
                       (co2, ReadReply(3, 4, (800,)).frame()[:-1] + b"\x00"))
    recs = [r for tx in txs for r in view.add(tx)]
    assert [(r["field"], r["status"], r["value"], r["raw"]) for r in recs] == [
        ("co2", "timeout", None, None), ("co2", "exception", None, None),
        ("co2", "garbled", None, None)]
    assert "SERVER DEVICE FAILURE" in recs[1]["error"]
    u = view.units[3]
    assert (u.timeouts, u.garbled, dict(u.exceptions)) == (1, 1, {4: 1})


def test_half_a_field_is_not_decoded() -> None:
    view = BusView([Known("irnet", profile("net-irnet-pro"), 1)])
    f = profile("net-irnet-pro").field("concentration")  # a float: two registers
    [tx] = transactions((ReadRequest(1, 4, f.address, 1).frame(),
                         ReadReply(1, 4, (0x4242,)).frame()))
    assert not [r for r in view.add(tx) if r["field"] == "concentration"]


def test_an_unknown_unit_is_raw_and_looks_like_the_profile_its_answers_fit() -> None:
    library = list(load_library().profiles.values())
    view = BusView([], library)
    p = profile("huiwen-aq")
    addr, co2 = p.field("slave_address"), p.field("co2")
    txs = transactions((ReadRequest(7, addr.table.read_function, addr.address, 1).frame(),
                        ReadReply(7, 3, (7,)).frame()),
                       (ReadRequest(7, co2.table.read_function, co2.address, 1).frame(),
                        ReadReply(7, 4, (650,)).frame()))
    recs = [r for tx in txs for r in view.add(tx)]
    assert recs[-1]["profile"] is None and recs[-1]["field"] == "input:30009"
    assert recs[-1]["value"] == 650
    assert view.units[7].hints[0].startswith("huiwen-aq (")
    # an address register that does not hold its own address: not a Huiwen module
    view2 = BusView([], library)
    for tx in transactions((ReadRequest(8, addr.table.read_function, addr.address, 1).frame(),
                            ReadReply(8, 3, (9,)).frame()),
                           (ReadRequest(8, co2.table.read_function, co2.address, 1).frame(),
                            ReadReply(8, 4, (650,)).frame())):
        view2.add(tx)
    assert not any(h.startswith("huiwen-aq") for h in view2.units[8].hints)


def test_line_troubles_are_counted_and_shown() -> None:
    view = BusView([HUIWEN])
    s = Stream(F)
    txs = s.feed(b"\x00", T0) + s.feed(ReadReply(9, 4, (1,)).frame(), T0 + 0.1) + s.close()
    for tx in txs:
        view.add(tx)
    assert (view.noise, view.orphans) == (1, 1)
    lines = [frame_line(tx, view, []) for tx in txs]
    assert lines[0].endswith("STRAY BYTES: stray bytes 00")
    assert "REPLY TO NO REQUEST" in lines[1]


def test_frame_lines_and_the_table_name_what_happened() -> None:
    from io import StringIO

    from rich.console import Console

    view = BusView([HUIWEN])
    write = WriteSingle(3, 6, 0x9C41, 3).frame()
    txs = transactions((ReadRequest(3, 4, 30009, 1).frame(), ReadReply(3, 4, (800,)).frame()),
                       (write, write))
    lines = [frame_line(tx, view, view.add(tx)) for tx in txs]
    assert "air (huiwen-aq@3)  fc04 read input 0x7539 x1  reply 20.0 ms  co2=800 ppm" in lines[0]
    assert lines[1].endswith("written (echoed)")
    console = Console(file=StringIO(), width=100)
    console.print(render(view, T0 + 2, "test"))
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert "air" in text and "co2" in text and "800" in text and "20.0 ms" in text


def test_a_float_register_holding_nan_gives_null_not_bare_nan() -> None:
    from rtupoll.model.interpret import field_words
    from rtupoll.ui.records import to_json

    irnet = profile("net-irnet-pro")
    f = irnet.field("concentration")
    words = field_words(f, float("nan"))
    view = BusView([Known("irnet", irnet, 1)])
    [tx] = transactions((ReadRequest(1, f.table.read_function, f.address, 2).frame(),
                         ReadReply(1, 4, tuple(words)).frame()))
    [rec] = [r for r in view.add(tx) if r["field"] == "concentration"]
    assert rec["value"] is None and rec["text"] == "NaN"
    assert "NaN" not in to_json({k: v for k, v in rec.items() if k != "text"})
