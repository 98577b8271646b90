"""Serving: pty and TCP transports, wire timing, clean start and stop, moving values."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import RawPort

from rtupoll.rtu import Framing
from rtupoll.rtu.messages import ReadReply, ReadRequest
from rtupoll.sim.runner import SimulatedBus, running, simulated_bus

Sim = Callable[..., SimulatedBus]
Raw = Callable[..., RawPort]
READ = ReadRequest(1, 4, 0x0006, 2).frame()


def test_a_client_can_close_and_reopen_the_pty(sim: Sim, raw_port: Raw) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    first = raw_port(bus.port)
    reply = first.transact(READ, 9)
    first.close()
    again = RawPort(bus.port)
    try:
        assert again.transact(READ, 9) == reply
    finally:
        again.close()
    first.fd = os.open("/dev/null", os.O_RDONLY)  # the fixture closes it once more


def test_link_is_a_stable_name_for_the_pty_and_goes_away_on_stop(tmp_path: Path,
                                                                   raw_port: Raw) -> None:
    link = tmp_path / "rtu0"
    with simulated_bus(["huiwen-aq@3"], link=str(link), tick=None) as bus:
        assert link.is_symlink() and os.readlink(link) == bus.port
        assert raw_port(str(link)).transact(ReadRequest(3, 3, 40001, 1).frame(), 7) \
            == ReadReply(3, 3, (3,)).frame()
    assert not link.exists() and not link.is_symlink()


def test_rtu_over_tcp_serves_the_same_frames(sim: Sim, raw_port: Raw) -> None:
    bus = sim("net-irnet-pro@1", tcp=True, tick=None, sets=["net-irnet-pro@1.concentration=-20"])
    assert bus.port.startswith("tcp://127.0.0.1:")
    assert raw_port(bus.port).transact(READ, 9) == bytes.fromhex("01 04 04 00 00 A0 C1 42 14")


def test_stop_releases_the_thread_the_pty_and_the_descriptors() -> None:
    fds = len(os.listdir("/proc/self/fd"))
    bus = simulated_bus(["net-irnet-pro@1"]).start()
    port = bus.port
    assert bus.alive and bus in running() and os.path.exists(port)
    bus.stop()
    assert not bus.alive and bus not in running()
    assert len(os.listdir("/proc/self/fd")) == fds
    bus.stop()  # idempotent


def test_starting_five_devices_in_a_fresh_process() -> None:
    code = textwrap.dedent("""
        from rtupoll.sim.runner import simulated_bus
        with simulated_bus() as bus:  # profiles not yet loaded in this process
            print(len(bus.device_list()))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=30, check=True).stdout.split()
    assert out == ["5"]


def test_the_leak_check_fails_a_test_that_leaves_a_bus_running(
        pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch) -> None:
    # run in this process: the conftest's module code sets its own profile cache
    # directory, which this test's end puts back
    monkeypatch.setenv("XDG_CACHE_HOME", os.environ["XDG_CACHE_HOME"])
    tests = Path(__file__).parents[1]
    pytester.makeconftest((tests / "conftest.py").read_text())
    pytester.makepyfile(cpu_report=(tests / "cpu_report.py").read_text())  # its plugin
    pytester.makepyfile(textwrap.dedent("""
        from rtupoll.sim.runner import simulated_bus

        def test_leaks():
            simulated_bus(["huiwen-aq@3"]).start()
    """))
    result = pytester.runpytest_inprocess("-p", "no:cacheprovider", "-p", "no:hypothesispytest",
                                          "-p", "no:xdist")
    result.assert_outcomes(passed=1, errors=1)
    result.stdout.fnmatch_lines(["*left 1 simulated bus(es) running*"])


# -- wire timing ------------------------------------------------------------------

@pytest.mark.timing
@pytest.mark.parametrize(("baud", "turnaround"), [(9600, None), (115200, 0.0)])
def test_wire_timing_takes_the_real_time_of_both_frames(sim: Sim, raw_port: Raw, baud: int,
                                                        turnaround: float | None,
                                                        jitter: float) -> None:
    """The simulator's thread holds a reply back for the real time of the line: never less,
    and (run alone, in the timing group) not more than a few wake-ups of a thread late."""
    bus = sim("net-irnet-pro@1", baudrate=baud, turnaround=turnaround, tick=None)
    port = raw_port(bus.port, baud)
    fr = Framing(baud)
    ta = 0.02 if turnaround is None else turnaround  # the profile's limits.turnaround
    expected = fr.wire_time(8) + fr.silence + ta + fr.wire_time(9)
    times = []
    for _ in range(3):
        sent = port.send(READ)
        assert len(port.read(9, timeout=1)) == 9
        times.append(time.monotonic() - sent)
        time.sleep(fr.silence)
    assert expected - 0.001 <= min(times) <= expected + 0.02 + 4 * jitter, (expected, times)


@pytest.mark.timing
def test_without_a_baud_rate_replies_are_not_held_back(sim: Sim, raw_port: Raw,
                                                       jitter: float) -> None:
    bus = sim("net-irnet-pro@1", tick=None)
    port = raw_port(bus.port)
    times = []
    for _ in range(3):
        sent = port.send(READ)
        assert len(port.read(9, timeout=1)) == 9
        times.append(time.monotonic() - sent)
    # not held back (a timed line would take its turnaround too)
    assert min(times) < 0.5 + 4 * jitter


# -- values -----------------------------------------------------------------------

def test_values_move_within_their_range_and_a_seed_replays_them(sim: Sim) -> None:
    def story(seed: int) -> list[int]:
        bus = sim("huiwen-aq@3", tick=None, seed=seed, sets=["huiwen-aq@3.pm25=10"])
        seen = []
        for _ in range(60):
            bus.advance()
            co2 = bus.get(3, "co2").value
            assert isinstance(co2, int) and 400 <= co2 <= 5000
            assert bus.get(3, "pm25").value == 10  # pinned: never moves
            seen.append(co2)
        return seen

    a = story(1)
    assert len(set(a)) > 10
    assert a == story(1)
    assert a != story(2)


def test_error_codes_and_flags_show_up_now_and_then(sim: Sim) -> None:
    bus = sim("net-irnet-pro@1", tick=None, seed=3)
    errors: list[object] = []
    warnings: list[tuple[str, ...]] = []
    for _ in range(2000):
        bus.advance()
        errors.append(bus.get(1, "error").value)
        warnings.append(tuple(bus.get(1, "warning").value))  # type: ignore[arg-type]
    assert len(set(errors)) > 1 and len(set(warnings)) > 1  # they do show up ...
    assert errors.count("NO_ERROR") > 0.9 * len(errors)  # ... now and then, not always
    assert warnings.count(()) > 0.9 * len(warnings)


def test_values_move_with_time(sim: Sim) -> None:
    bus = sim("huiwen-aq@3", tick=0.02)
    before = bus.registers(3, "input", 30006, 8)
    time.sleep(0.1)
    bus.get(3, "co2")  # values catch up when looked at
    assert bus.device(3).ticks >= 4
    assert bus.registers(3, "input", 30006, 8) != before


def test_stopping_a_tcp_bus_hangs_up_on_its_clients() -> None:
    import socket

    from rtupoll.sim.runner import simulated_bus

    with simulated_bus(["huiwen-aq@3"], tcp=True, tick=None) as bus:
        host, _, port = bus.port[len("tcp://"):].rpartition(":")
        client = socket.create_connection((host, int(port)), timeout=30)  # (a hang guard)
        client.sendall(ReadRequest(3, 3, 40001, 1).frame())
        assert len(client.recv(64)) == 7
    try:
        assert client.recv(64) == b""  # end-of-file: the "gateway" went away
    finally:
        client.close()
