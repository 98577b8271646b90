"""An address change's --dry-run frames, before the bus (rtupoll.jobs.commission)."""

from __future__ import annotations

from rtupoll.config.library import load_one
from rtupoll.jobs.commission import dry_run
from rtupoll.model.addressing import Change


def test_dry_run_frames_match_the_manuals() -> None:
    frames = dry_run(Change(load_one("huiwen-aq"), 1, 12))
    hexes = [f for f, _ in frames]
    assert "01 03 9C 41 00 01 FA 4E" in hexes  # the manual's own "read slave address" frame
    assert hexes[2] == "01 06 9C 41 00 0C F7 8B"  # FC06 to holding 40001 (wire 0x9C41)


def test_dry_run_marks_the_byte_a_read_modify_write_keeps() -> None:
    frames = dry_run(Change(load_one("banner-ez-array"), 1, 7))
    write = next(f for f, why in frames if why.startswith("write"))
    # FC16 to 41000 (wire 0xA028): high byte kept from the read, so it and the CRC are unknown
    assert write == "01 10 A0 28 00 01 02 ?? 07 ?? ??"
