"""The planner: fewest block reads within a profile's limits, never touching what it must not.

Table-driven for the five seed profiles (the blocks a person would choose from each
manual), then hypothesis properties over random register maps: every field covered
exactly once, no block over the limit, no forbidden register read, gaps within
``max_gap``, and the block count equal to the optimum found independently by dynamic
programming.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from itertools import pairwise

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rtupoll.config.library import load_one
from rtupoll.errors import FrameError, RefusedError
from rtupoll.model.codec import DataType, Layout
from rtupoll.model.interpret import field_words
from rtupoll.model.planner import Block, decode_block, for_variant, plan, read_limit
from rtupoll.model.profile import Addressing, Field, Limits, Poll, Profile
from rtupoll.rtu import Table

IN, HOLD = Table.INPUT, Table.HOLDING


def shape(blocks: Sequence[Block]) -> list[tuple[Table, int, int, tuple[str, ...]]]:
    return [(b.table, b.address, b.count, tuple(f.name for f in b.fields)) for b in blocks]


def names(profile: Profile, *wanted: str) -> list[Field]:
    return [profile.field(n) for n in wanted]


# -- the seed profiles --------------------------------------------------------

SEED_DEFAULTS = {
    "net-irnet-pro": [(IN, 0x0004, 6, ("temperature", "concentration", "error", "warning"))],
    "radar-level": [(HOLD, a, 1, (n,)) for a, n in
                    ((0, "air_gap_cm"), (1, "air_gap_mm"), (2, "level_cm"), (3, "level_mm"),
                     (0x10, "status"))],
    "huiwen-aq": [
        (IN, 30006, 8, ("pm25", "tvoc", "hcho", "co2", "temperature", "humidity")),
        (IN, 30036, 4, ("pm25_level", "tvoc_level", "hcho_level", "co2_level")),
        (IN, 30106, 6, ("pm25_failure", "tvoc_failure", "hcho_failure", "co2_failure",
                        "th_failure")),
    ],
    "co2meter-an117": [(IN, 1, 1, ("co2",))],
    "banner-ez-array": [
        (IN, 30001, 2, ("measurement_1", "measurement_2")),
        (IN, 30027, 7, ("first_bad_channel", "error_code", "outputs", "analog_1_dac",
                        "analog_2_dac")),
    ],
}


@pytest.mark.parametrize("pid", sorted(SEED_DEFAULTS))
def test_default_poll_of_each_seed_profile(pid: str) -> None:
    p = load_one(pid)
    assert shape(plan(p.default_fields(), p)) == SEED_DEFAULTS[pid]


def test_irnet_everything_readable() -> None:
    """max_gap 0: only adjacent fields share a request; the strings form one block."""
    p = load_one("net-irnet-pro")
    blocks = plan([f for f in p.fields if f.poll is not Poll.NEVER], p)
    assert [(b.table, b.address, b.count) for b in blocks] == [
        (IN, 0x0004, 12), (IN, 0x001E, 2), (IN, 0x0400, 1),
        (HOLD, 0x0016, 4), (HOLD, 0x0026, 20), (HOLD, 0x003C, 4), (HOLD, 0x007C, 1),
        (HOLD, 0x0200, 2)]
    assert blocks[2].fields == (p.field("data_structure"),)  # alone: true


def test_irnet_variant_0_drops_the_fields_it_lacks() -> None:
    p = load_one("net-irnet-pro")
    wanted = names(p, "full_scale", "uart_speed", "calibration_gas_level")
    assert [b.fields[0].name for b in plan(wanted, p, variant=0)] == ["full_scale"]
    assert len(plan(wanted, p, variant=1)) == 3
    assert len(plan(wanted, p)) == 3  # variant unknown: read what was asked


def test_banner_never_touches_the_peak_registers() -> None:
    """30521/30522 reset the analog peaks when read: a block may not bridge them."""
    p = load_one("banner-ez-array")
    around = names(p, "carpet_nap", "carpet_edge", "special")
    assert shape(plan(around, p)) == [(IN, 30520, 1, ("carpet_nap",)),
                                      (IN, 30523, 2, ("carpet_edge", "special"))]
    asked = names(p, "carpet_nap", "analog_1_peak", "carpet_edge")
    assert shape(plan(asked, p)) == [(IN, 30520, 1, ("carpet_nap",)),
                                     (IN, 30521, 1, ("analog_1_peak",)),
                                     (IN, 30523, 1, ("carpet_edge",))]


def test_banner_on_request_block_and_shared_byte_register() -> None:
    p = load_one("banner-ez-array")
    measurements = [f for f in p.fields if 30500 <= int(f.written) <= 30524
                    and f.poll is not Poll.NEVER]
    assert [(b.address, b.count) for b in plan(measurements, p)] == [(30500, 21), (30523, 2)]
    (block,) = plan(names(p, "dip_switches", "error_code"), p)
    assert (block.address, block.count) == (30030, 1)
    dip, err = decode_block(block, [0x0305])
    assert (dip.value, err.value, err.code) == (5, "SENSOR_ERROR (3)", 3)


def test_gap_bridging_follows_max_gap() -> None:
    """Huiwen's 30010/30011 are unmapped: bridged with max_gap 4, not with 1."""
    p = load_one("huiwen-aq")
    first = names(p, "co2", "temperature")
    assert shape(plan(first, p)) == [(IN, 30009, 4, ("co2", "temperature"))]
    tight = dataclasses.replace(p, limits=dataclasses.replace(p.limits, max_gap=1))
    assert len(plan(first, tight)) == 2


def test_max_registers_splits_blocks() -> None:
    p = load_one("huiwen-aq")
    small = dataclasses.replace(p, limits=dataclasses.replace(p.limits, max_registers=3))
    blocks = plan(p.default_fields(), small)
    assert [(b.address, b.count) for b in blocks] == [
        (30006, 3), (30009, 1), (30012, 2), (30036, 3), (30039, 1), (30106, 3), (30109, 3)]


def test_radar_reads_every_register_alone() -> None:
    p = load_one("radar-level")
    blocks = plan(list(p.fields), p)
    assert all(b.count == 1 and len(b.fields) == 1 for b in blocks)
    assert len(blocks) == len(p.fields)


def test_refusals() -> None:
    p = load_one("radar-level")
    no_fc3 = dataclasses.replace(p, limits=dataclasses.replace(p.limits,
                                                                functions=frozenset({6})))
    with pytest.raises(RefusedError, match="function 3"):
        plan(p.default_fields(), no_fc3)
    wide = _field("big", HOLD, 0, 4)
    q = _profile([wide], max_registers=2)
    with pytest.raises(RefusedError, match="4 registers wide"):
        plan([wide], q)
    lo = _field("lo", HOLD, 5, 1, poll=Poll.NEVER, dtype=DataType.U8)
    hi = dataclasses.replace(lo, name="hi", poll=Poll.DEFAULT,
                             layout=dataclasses.replace(lo.layout, byte="high"))
    with pytest.raises(RefusedError, match="never be read"):
        plan([hi], _profile([lo, hi]))


def test_helpers_and_dedup() -> None:
    p = load_one("net-irnet-pro")
    assert (read_limit(p, Table.INPUT), read_limit(p, Table.COIL)) == (125, 2000)
    assert len(for_variant(p.fields, 0)) == len(p.fields) - 2
    twice = plan([p.field("error"), p.field("error")], p)
    assert shape(twice) == [(IN, 8, 1, ("error",))]


def test_decode_block_interprets_each_field() -> None:
    p = load_one("net-irnet-pro")
    (block,) = plan(p.default_fields(), p)
    # the manual's golden reply: wire bytes 00 00 A0 C1 are -20.0 (DCBA)
    words = (*field_words(p.field("temperature"), 296.5), 0x0000, 0xA0C1, 0x0000, 0x0011)
    temp, conc, err, warn = decode_block(block, words)
    assert temp.value == 296.5
    assert conc.value == -20.0 and conc.raw == (0x0000, 0xA0C1)
    assert err.value == "NO_ERROR"
    assert warn.value == ["WARMUP_WARNING", "INVALID_READINGS_WARNING"]
    with pytest.raises(FrameError):
        decode_block(block, words[:-1])


# -- properties over random register maps --------------------------------------

def _field(name: str, table: Table, address: int, words: int, *, poll: Poll = Poll.DEFAULT,
           alone: bool = False, dtype: DataType | None = None) -> Field:
    t = dtype or {1: DataType.U16, 2: DataType.U32, 4: DataType.U64}[words]
    return Field(name=name, table=table, address=address, layout=Layout(t, words), poll=poll,
                 alone=alone)


def _profile(fields: Sequence[Field], *, max_registers: int = 125, max_gap: int = 0) -> Profile:
    return Profile(id="prop", vendor="v", model="m", manual="x", addressing=Addressing.PDU,
                   fields=tuple(fields),
                   limits=Limits(max_registers=max_registers, max_gap=max_gap,
                                 functions=frozenset({1, 2, 3, 4})))


@st.composite
def register_maps(draw: st.DrawFn) -> tuple[Profile, list[Field]]:
    """A profile with non-overlapping fields in two tables, and a request over it."""
    fields: list[Field] = []
    for table in (IN, HOLD):
        at = draw(st.integers(0, 20))
        for _ in range(draw(st.integers(0, 14))):
            at += draw(st.integers(0, 7))
            width = draw(st.sampled_from([1, 1, 1, 2, 4]))
            poll = draw(st.sampled_from([Poll.DEFAULT] * 4 + [Poll.ON_REQUEST, Poll.NEVER]))
            alone = draw(st.integers(0, 7)) == 0
            fields.append(_field(f"f{len(fields)}", table, at, width, poll=poll, alone=alone))
            at += width
    limit = draw(st.integers(4, 16))
    profile = _profile(fields, max_registers=limit, max_gap=draw(st.integers(0, 5)))
    asked = [f for f in fields if f.poll is Poll.DEFAULT or draw(st.booleans())]
    return profile, draw(st.permutations(asked))


def _optimum(fields: Sequence[Field], p: Profile) -> int:
    """Fewest blocks, by dynamic programming over runs of fields in address order.

    A block reads a contiguous range, so the fields it serves are consecutive in
    address order; a run is feasible when its span fits and every gap is bridgeable.
    """
    blocked = {(g.table, r) for g in p.fields if g.alone or g.poll is Poll.NEVER
               for r in range(g.address, g.end)}
    total = sum(1 for f in fields if f.alone or f.poll is Poll.NEVER)
    for table in (IN, HOLD):
        run = sorted((f for f in fields if f.table is table and not f.alone
                      and f.poll is not Poll.NEVER), key=lambda f: f.address)
        best = [0] + [len(run) + 1] * len(run)
        for k in range(1, len(run) + 1):
            for i in range(k):
                part = run[i:k]
                ok = part[-1].end - part[0].address <= p.limits.max_registers and all(
                    b.address - a.end <= p.limits.max_gap
                    and not any((table, r) in blocked for r in range(a.end, b.address))
                    for a, b in pairwise(part))
                if ok:
                    best[k] = min(best[k], best[i] + 1)
        total += best[len(run)]
    return total


@given(register_maps())
def test_plan_properties(case: tuple[Profile, list[Field]]) -> None:
    profile, asked = case
    before = list(asked)
    blocks = plan(asked, profile)
    assert asked == before  # inputs untouched

    served = [f.name for b in blocks for f in b.fields]
    assert sorted(served) == sorted(f.name for f in asked)  # every field exactly once

    never = {(f.table, r): f.name for f in profile.fields if f.poll is Poll.NEVER
             for r in range(f.address, f.end)}
    alone = {(f.table, r): f.name for f in profile.fields if f.alone
             for r in range(f.address, f.end)}
    for b in blocks:
        assert 1 <= b.count <= profile.limits.max_registers
        assert b.address == min(f.address for f in b.fields)  # no wasted edges
        assert b.end == max(f.end for f in b.fields)
        assert all(f.table is b.table and b.address <= f.address and f.end <= b.end
                   for f in b.fields)
        touched = {(b.table, r) for r in range(b.address, b.end)}
        for reg in touched:
            owner = never.get(reg) or alone.get(reg)
            if owner is not None:  # only its own, explicitly asked, single-field block
                assert [f.name for f in b.fields] == [owner]
        covered = sorted(r for f in b.fields for r in range(f.address, f.end))
        gaps = [hi - lo - 1 for lo, hi in pairwise(covered) if hi - lo > 1]
        assert all(g <= profile.limits.max_gap for g in gaps)

    assert len(blocks) == _optimum(asked, profile)
    assert plan(list(reversed(asked)), profile) == blocks  # order-independent


@given(register_maps())
def test_decode_block_hands_each_field_its_own_registers(
        case: tuple[Profile, list[Field]]) -> None:
    profile, asked = case
    for block in plan(asked, profile):
        words = [(block.address + i) & 0xFFFF for i in range(block.count)]
        for f, fv in zip(block.fields, decode_block(block, words), strict=True):
            assert fv.field is f
            assert fv.raw == tuple(range(f.address, f.end))
