"""``guess --known``: from one value read off a device, the settings that give it, on the
examples printed in the seed devices' manuals (and every bundled profile's golden data)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from cli_runner import rtupoll

from rtupoll.config.library import load_one
from rtupoll.errors import UsageError
from rtupoll.model.codec import ByteOrder, DataType
from rtupoll.model.known import Known, Solution, parse_known, solve
from rtupoll.model.profile import Field

GOLDEN = Path(__file__).parents[1] / "fixtures" / "golden"
SEEDS = ["net-irnet-pro", "huiwen-aq", "co2meter-an117", "banner-ez-array", "radar-level"]


def _registers(case: dict[str, Any]) -> tuple[int, tuple[int, ...]] | None:
    """(first wire address, register words) of a golden case's read, if it has one."""
    if "registers" in case:
        return case["start"], tuple(int(w, 16) for w in str(case["registers"]).split())
    raw = bytes(int(b, 16) for b in re.findall(r"\b[0-9A-Fa-f]{2}\b", str(case["frames"])))
    if len(raw) <= 8 or raw[1] not in (3, 4):
        return None
    reply = raw[8:]
    return int.from_bytes(raw[2:4], "big"), tuple(
        int.from_bytes(reply[3 + k : 5 + k], "big") for k in range(0, reply[2], 2))


def _known_values(pids: list[str]) -> list[Any]:
    out = []
    for pid in pids:
        profile = load_one(pid)
        data = yaml.safe_load((GOLDEN / f"{pid}.yaml").read_text(encoding="utf-8"))
        for n, case in enumerate(data.get("cases", [])):
            read = _registers(case)
            for name, value in (case.get("expect") or {}).items():
                f = profile.field(name)
                lay = f.layout
                if (read is None or isinstance(value, (str, bool)) or not value or f.scale_by
                        or f.transform
                        or lay.offset or lay.width
                        or lay.type.value not in ("u16", "i16", "u32", "i32", "f32", "f64")
                        or round(math.log10(abs(lay.scale))) != math.log10(abs(lay.scale))
                        or not read[0] <= f.address < read[0] + len(read[1])):
                    continue  # not a number a display shows from plain registers
                out.append(pytest.param(pid, name, read, value, id=f"{pid}[{n}].{name}"))
    return out


@pytest.mark.parametrize(("pid", "name", "read", "value"), _known_values(SEEDS))
def test_a_seed_manuals_example_is_solved_to_the_profiles_own_setting(
        pid: str, name: str, read: tuple[int, tuple[int, ...]], value: float) -> None:
    f = load_one(pid).field(name)
    found = solve(read[1], read[0], f.address, parse_known(str(value)))
    assert found, f"nothing gives {value}"
    assert _setting(found[0]) == _profiles(f, value), found[:3]


LIBRARY = sorted(p.stem for p in GOLDEN.glob("*.yaml"))


@pytest.mark.parametrize(("pid", "name", "read", "value"), _known_values(LIBRARY))
def test_every_golden_value_is_solved_with_the_profiles_setting_among_the_answers(
        pid: str, name: str, read: tuple[int, tuple[int, ...]], value: float) -> None:
    f = load_one(pid).field(name)
    found = solve(read[1], read[0], f.address, parse_known(str(value)))
    settings = [_setting(s) for s in found]
    assert _profiles(f, value) in settings, settings


UNSIGNED = {DataType.I16: DataType.U16, DataType.I32: DataType.U32}


def _setting(s: Solution) -> tuple[int, DataType, ByteOrder, float]:
    return s.address, s.type, s.order, s.scale


def _profiles(f: Field, value: float) -> tuple[int, DataType, ByteOrder, float]:
    """The profile's setting; a signed type reads a value >= 0 as its unsigned one does,
    so one known value cannot tell them apart (the solver names the unsigned)."""
    lay = f.layout
    dtype = UNSIGNED.get(lay.type, lay.type) if value >= 0 else lay.type
    return f.address, dtype, lay.order, lay.scale


def test_an_off_by_one_is_found_as_one_not_taken_for_a_byte_order() -> None:
    """OpenEMS#86: every permutation was tried when the manual's numbering was the fault.
    A float at wire 0x0000 (the manual's 30001), asked about at 1 (its number, 1-based)."""
    words = (0x4367, 0x6666, 0x0000, 0x0000)  # 231.4 as an f32, ABCD, then a zero float
    found = solve(words, 0, 1, parse_known("231.4"))
    best = found[0]
    assert (best.offset, best.type, best.order) == (-1, DataType.F32, ByteOrder.ABCD)
    assert best.setting == "address: 0x0000, type: f32, order: ABCD"


def test_a_scaled_integer_and_its_precision() -> None:
    found = solve((0x0908,), 10, 10, parse_known("231.2"))  # 2312 tenths of a volt
    assert found[0].setting == "address: 0x000A, type: u16, scale: 0.1"
    assert found[0].text == "231.2"
    assert parse_known("231.20") == Known(231.2, 0.005, 2)  # written to the hundredth
    assert [s.text for s in solve((0x0908,), 10, 10, parse_known("231.20"))][:1] == ["231.20"]
    assert solve((0x0909,), 10, 10, parse_known("231.20")) == []  # 231.3 is not 231.20


@pytest.mark.parametrize("text", ["abc", "nan", "inf", ""])
def test_a_known_value_that_is_no_number_is_one_line(text: str) -> None:
    with pytest.raises(UsageError, match="--known"):
        parse_known(text)


def test_guess_known_end_to_end_on_a_simulated_irnet(sim: Any) -> None:
    bus = sim("net-irnet-pro@1", tick=None, sets=["net-irnet-pro@1.concentration=1234.5"])
    run = rtupoll("guess", "-p", bus.port, "-b", "4800", "-a", "1", "input:6",
                  "--known", "1234.5", "--format", "json")
    assert run.returncode == 0, run.stderr
    best = json.loads(run.stdout.splitlines()[0])
    assert (best["address"], best["type"], best["order"]) == (6, "f32", "DCBA")
    checked = rtupoll("guess", "-p", bus.port, "-b", "4800", "net-irnet-pro@1",
                      "--known", "concentration=1234.5")
    assert checked.returncode == 0, checked.stderr
    assert "net-irnet-pro concentration: its setting gives it" in checked.stdout
    wrong = rtupoll("guess", "-p", bus.port, "-b", "4800", "net-irnet-pro@1",
                    "--known", "concentration=99.5")
    assert wrong.returncode == 1 and "No setting within 2 registers" in wrong.stdout
