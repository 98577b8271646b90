"""Each command imports only what it uses (``python -X importtime``): every start of
rtupoll pays for what it imports, a person's and each of the test suite's ~285.

- no event loop (asyncio, and with it ssl, socket, subprocess) where nothing is awaited:
  a dry run of set-address, guess on given words, decode;
- no YAML parser where no YAML is read: poll of named devices (no site file), decode,
  a read whose profile is in the profile cache;
- no profile library for decode without --profile;
- and for a one-shot read (tests/cli/test_read_imports.py): no csv module but for the csv
  format, the profile cache read with the C unpickler alone (not pickle.py).
"""

from __future__ import annotations

from collections.abc import Callable

from test_read_imports import imported, loaded

from rtupoll.config.library import load_library, load_one
from rtupoll.sim.runner import SimulatedBus

NO_LOOP = ("asyncio", "pymodbus", "ssl")


def test_a_set_address_dry_run_starts_no_event_loop() -> None:
    load_library()  # every profile (it avoids their reserved addresses) in the profile
    # cache, the test run's own (conftest.py)
    modules = imported("set-address", "--port", "/dev/null", "--dry-run", "radar-level@1", "11")
    assert "rtupoll.jobs.commission" in modules  # it planned the change
    # not even the async bus (the modbus library is in NO_LOOP)
    assert [p for p in (*NO_LOOP, "rtupoll.io.bus", "yaml", "csv") if loaded(modules, p)] == []


def test_guess_on_given_words_reads_no_device() -> None:
    modules = imported("guess", "--words", "--format", "json", "0000", "A0C1")
    assert "rtupoll.model.guess" in modules
    assert [p for p in (*NO_LOOP, "csv", "rich") if loaded(modules, p)] == []


def test_decode_without_a_profile_loads_no_library() -> None:
    modules = imported("decode", "--format", "json", "01030000000AC5CD")
    assert "rtupoll.rtu.capture" in modules
    unused = (*NO_LOOP, "yaml", "csv", "rich", "pickle", "rtupoll.config.library")
    assert [p for p in unused if loaded(modules, p)] == []


def test_poll_of_named_devices_parses_no_yaml(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    load_one("huiwen-aq")
    modules = imported("poll", "--port", bus.port, "--once", "--format", "json", "huiwen-aq@1")
    assert "rtupoll.config.site" in modules and "rtupoll.jobs.scheduler" in modules
    assert [p for p in ("yaml", "rtupoll.config.yamlsrc", "csv") if loaded(modules, p)] == []


def test_a_write_runs_on_the_blocking_bus(sim: Callable[..., SimulatedBus]) -> None:
    """A write awaits only the bus, as a read does: no event loop, no pymodbus."""
    bus = sim("xy-md02@2", tick=None)
    load_one("xy-md02")
    modules = imported("write", "--port", bus.port, "--yes", "--format", "json", "xy-md02@2",
                       "temperature_correction=1.5")
    assert "rtupoll.io.syncbus" in modules and "rtupoll.jobs.writes" in modules
    assert [p for p in (*NO_LOOP, "rtupoll.io.bus", "yaml", "rich") if loaded(modules, p)] == []
    assert bus.get(2, "temperature_correction").value == 1.5  # and it wrote


def test_guess_reads_on_the_blocking_bus(sim: Callable[..., SimulatedBus]) -> None:
    bus = sim("huiwen-aq@1", tick=None)
    modules = imported("guess", "--port", bus.port, "--address", "1", "--format", "json",
                       "input:30009:1")
    assert "rtupoll.io.syncbus" in modules and "rtupoll.model.guess" in modules
    assert [p for p in (*NO_LOOP, "rtupoll.io.bus") if loaded(modules, p)] == []
