"""Serial ports pyserial opens over a network, for every command, with the same line
discipline: ``rfc2217://`` against a real RFC 2217 server (pyserial's ``PortManager``
bridging TCP to the simulator's pty, tests/rfc2217_server.py: the baud rate is
negotiated onto the pty, where the simulator answers only at its line's speed) and
``socket://`` against the simulator's TCP mode. Neither has a descriptor ``os.read``
could read (RFC 2217's client has no ``fileno``; ``socket://``'s is a socket), so these
run the portable wait (``rtupoll.io.waits.PortWait``) for real, and pymodbus's
``write_timeout = 0``, which RFC 2217's client refuses, must not stop ``poll`` or
``scan``. Values are checked against the simulator's."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_runner import rtupoll
from conftest import PATIENT
from rfc2217_server import Rfc2217Server

from rtupoll.io import port_settings, waits
from rtupoll.io.syncbus import SyncBus
from rtupoll.rtu import Table
from rtupoll.sim.runner import SimulatedBus

Sim = Callable[..., SimulatedBus]
# pyserial's RFC 2217 client names its reader thread the old way (Python 3.10's warning)
pytestmark = pytest.mark.filterwarnings(r"ignore:set(Daemon|Name)\(\) is deprecated")
DEVICES = ("huiwen-aq@3", "radar-level@4")


@pytest.fixture(params=["rfc2217", "socket"])
def line(request: pytest.FixtureRequest, sim: Sim) -> Iterator[tuple[str, SimulatedBus]]:
    """(the port a command is given, the simulated bus behind it)."""
    if request.param == "rfc2217":
        bus = sim(*DEVICES, baudrate=9600, tick=None)
        with Rfc2217Server(bus.port) as url:
            yield url, bus
    else:
        bus = sim(*DEVICES, baudrate=9600, tick=None, tcp=True)
        yield bus.port.replace("tcp://", "socket://"), bus


def records(stdout: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in stdout.splitlines()]


def test_the_portable_wait_is_what_such_a_port_gets(line: tuple[str, SimulatedBus]) -> None:
    port, _ = line
    with SyncBus(port_settings.PortSettings(port)) as bus:
        assert isinstance(bus._take, waits.PortWait)  # no descriptor to os.read


def test_read(line: tuple[str, SimulatedBus]) -> None:
    port, bus = line
    bus.set(3, "co2", 777)
    ran = rtupoll("read", "-p", port, "-b", "9600", *PATIENT, "--format", "json",
                  "huiwen-aq@3", "co2", "temperature")
    assert ran.returncode == 0, ran.stderr
    got = {r["field"]: r["value"] for r in records(ran.stdout)}
    assert got == {"co2": 777, "temperature": bus.get(3, "temperature").value}


def test_poll_once(line: tuple[str, SimulatedBus]) -> None:
    port, bus = line
    bus.set(4, "level_cm", 123)
    ran = rtupoll("poll", "--once", "-p", port, "-b", "9600", *PATIENT, "--format", "json",
                  "huiwen-aq@3", "radar-level@4")
    assert ran.returncode == 0, ran.stderr
    got = {(r["device"], r["field"]): r["value"] for r in records(ran.stdout)}
    assert got[("radar-level@4", "level_cm")] == 123
    assert got[("huiwen-aq@3", "co2")] == bus.get(3, "co2").value
    assert {r["status"] for r in records(ran.stdout)} == {"ok"}


def test_write_reads_back_what_the_device_now_holds(line: tuple[str, SimulatedBus]) -> None:
    port, bus = line
    ran = rtupoll("write", "-p", port, "-b", "9600", *PATIENT, "--yes", "--format", "json",
                  "radar-level@4", "baud_rate=19200")
    assert ran.returncode == 0, ran.stderr
    assert records(ran.stdout)[0]["value"] == 19200
    assert bus.get(4, "baud_rate").value == 19200


def test_scan_finds_both_devices_and_only_them(line: tuple[str, SimulatedBus]) -> None:
    port, _ = line
    ran = rtupoll("scan", "-p", port, "-b", "9600", "--addresses", "2-5")
    assert ran.returncode == 0, ran.stderr
    assert "2 identified, 0 unknown or garbled" in ran.stderr
    assert "radar-level" in ran.stdout and "huiwen-aq" in ran.stdout


def test_guess(line: tuple[str, SimulatedBus]) -> None:
    port, bus = line
    bus.set(3, "co2", 1234)
    ran = rtupoll("guess", "-p", port, "-b", "9600", *PATIENT, "--address", "3",
                  "input:30009")  # co2
    assert ran.returncode == 0, ran.stderr
    assert "0x7539 (30009) │ u16  │                │ 1234" in ran.stdout


def test_sniff_listens_on_a_network_serial_port(sim: Sim, tmp_path: Path) -> None:
    """``sniff -p rfc2217://...``: the tap of a line served by an RFC 2217 server (an
    adapter on the pair, elsewhere), heard through the portable wait, values decoded."""
    from tests.sniff.test_sniff import mbpoll, records, sniffing

    tap = str(tmp_path / "tap")
    bus = sim("huiwen-aq@3", tick=None, tap=tap, sets=["huiwen-aq@3.co2=901"])
    with Rfc2217Server(tap) as url, sniffing(url, "--format", "json", "huiwen-aq@3",
                                             shown=1) as lines:
        mbpoll(bus.port, 3, Table.INPUT, 30009, 1)  # co2, 0x7539
    got = [r for r in records(lines) if r.get("field") == "co2"]
    assert got, lines
    assert got[0]["value"] == 901


def test_set_address_is_verified_at_the_new_address(line: tuple[str, SimulatedBus]) -> None:
    port, bus = line
    ran = rtupoll("set-address", "-p", port, "-b", "9600", "--timeout", "0.5", "--yes",
                  "radar-level@4", "11")
    assert ran.returncode == 0, ran.stderr
    assert "changed: answers at 11, silent at 4" in ran.stdout
    assert bus.addresses() == {"huiwen-aq@3": 3, "radar-level@4": 11}
