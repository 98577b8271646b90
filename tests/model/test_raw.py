"""Raw register specs: the three addressing forms, types and how reads are split
(rtupoll.model.raw)."""

from __future__ import annotations

import pytest

from rtupoll.errors import UsageError
from rtupoll.model.codec import ByteOrder, DataType
from rtupoll.model.interpret import interpret
from rtupoll.model.profile import Addressing
from rtupoll.model.raw import parse_spec, split_reads
from rtupoll.rtu import Table


def test_wire_address_is_the_default_and_direct_references_go_out_literally() -> None:
    spec = parse_spec("input:30006:5")
    assert (spec.table, spec.address, spec.count, spec.words) == (Table.INPUT, 30006, 5, 5)
    assert [f.name for f in spec.fields()][:2] == ["input:30006", "input:30007"]


def test_hex_start_is_labelled_in_hex() -> None:
    spec = parse_spec("holding:0x9C41")
    assert spec.address == 0x9C41 and spec.count == 1
    assert spec.label(0) == "holding:0x9C41"


def test_one_based_numbers_are_one_above_the_wire() -> None:
    spec = parse_spec("ir:4", addressing=Addressing.ONE_BASED)
    assert spec.address == 3 and spec.label(0) == "input:4"
    with pytest.raises(UsageError, match="start at 1"):
        parse_spec("input:0", addressing=Addressing.ONE_BASED)


@pytest.mark.parametrize(("text", "table", "wire"), [
    ("30006:5", Table.INPUT, 5),
    ("40001", Table.HOLDING, 0),
    ("input:30001", Table.INPUT, 0),
    ("400001", Table.HOLDING, 0),
    ("465536", Table.HOLDING, 65535),
    ("10003", Table.DISCRETE, 2),
])
def test_modicon_references_name_their_table(text: str, table: Table, wire: int) -> None:
    spec = parse_spec(text, addressing=Addressing.MODICON)
    assert (spec.table, spec.address) == (table, wire)


def test_modicon_reference_must_fit_the_named_table() -> None:
    with pytest.raises(UsageError, match="not a holding reference"):
        parse_spec("holding:30001", addressing=Addressing.MODICON)
    with pytest.raises(UsageError, match="not a Modicon reference"):
        parse_spec("20001", addressing=Addressing.MODICON)


def test_a_bare_number_without_modicon_is_refused_with_the_syntax() -> None:
    with pytest.raises(UsageError, match="needs --modicon"):
        parse_spec("30006:5")
    with pytest.raises(UsageError, match="TABLE:START"):
        parse_spec("input:")
    with pytest.raises(UsageError, match="numbers"):
        parse_spec("input:abc")


def test_count_counts_values_of_the_type() -> None:
    spec = parse_spec("input:6:2", type_name="f32", order=ByteOrder.DCBA)
    assert spec.words == 4 and [f.address for f in spec.fields()] == [6, 8]
    # IRNET golden frame: 00 00 A0 C1 is -20.0 in DCBA
    assert interpret(spec.fields()[0], (0x0000, 0xA0C1)).value == -20.0


def test_string_count_is_registers_of_one_text() -> None:
    spec = parse_spec("holding:0x2C:4", type_name="string")
    assert spec.count == 1 and spec.words == 4
    assert spec.layout.type is DataType.STRING


def test_coils_are_bits_whatever_the_type() -> None:
    spec = parse_spec("coil:0xD0")
    assert spec.layout.type is DataType.BOOL


def test_reads_are_split_at_the_device_limit_without_splitting_a_value() -> None:
    spec = parse_spec("input:0:10", type_name="u32")  # 20 registers
    assert split_reads(spec, 8) == [(0, 8), (8, 8), (16, 4)]
    assert split_reads(parse_spec("input:0:5"), 125) == [(0, 5)]


def test_a_run_past_the_last_register_is_refused() -> None:
    with pytest.raises(UsageError, match="past the last"):
        parse_spec("holding:0xFFFF:2")


def test_a_mistyped_table_is_named_with_a_suggestion() -> None:
    with pytest.raises(UsageError, match=r"'inptu:30006': unknown table 'inptu' \(did you mean "
                                         r"'input'\?\); tables: coil, discrete, input, holding"):
        parse_spec("inptu:30006")
