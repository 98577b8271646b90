"""'did you mean' as people type names: capitals, a prefix, a part of an id, a typo."""

from __future__ import annotations

import pytest
from cli_runner import rtupoll

from rtupoll.model.names import close_names

FIELDS = ["co2", "co2_level", "temperature", "temperature_correction", "humidity", "pm25"]
IDS = ["net-irnet-pro", "huiwen-aq", "eastron-sdm120", "eastron-sdm230", "radar-level"]


@pytest.mark.parametrize(("typed", "known", "meant"), [
    ("CO2", FIELDS, ["co2"]),  # the manual's capitals
    ("Temperature", FIELDS, ["temperature"]),
    ("temp", FIELDS, ["temperature", "temperature_correction"]),  # a prefix, shortest first
    ("humid", FIELDS, ["humidity"]),
    ("irnet", IDS, ["net-irnet-pro"]),  # a part of an id
    ("IRNET-PRO", IDS, ["net-irnet-pro"]),
    ("sdm", IDS, ["eastron-sdm120", "eastron-sdm230"]),
    ("huiwen_aq", IDS, ["huiwen-aq"]),  # - and _ are one to a person
    ("tmperature", FIELDS, ["temperature", "temperature_correction"]),  # a typo: difflib
    ("co", FIELDS, ["co2"]),  # too short for a prefix (co2_level is left out): a typo
    ("xyz", FIELDS, []),
    ("voltage", FIELDS, []),
])
def test_close_names_finds_what_a_person_meant(typed: str, known: list[str],
                                               meant: list[str]) -> None:
    assert close_names(typed, known, n=2) == meant


@pytest.mark.parametrize(("args", "hint"), [
    (["huiwen-aq@3", "CO2"], "(did you mean 'co2'?)"),
    (["huiwen-aq@3", "temp"], "(did you mean 'temperature'"),
    (["irnet@1"], "no profile 'irnet' (did you mean 'net-irnet-pro'?)"),
    (["IRNET-PRO@1"], "(did you mean 'net-irnet-pro'?)"),
])
def test_read_says_what_was_meant_before_opening_a_port(args: list[str], hint: str) -> None:
    run = rtupoll("read", "-p", "/dev/null", *args)
    assert run.returncode == 2
    assert hint in run.stderr and len(run.stderr.splitlines()) == 1, run.stderr
