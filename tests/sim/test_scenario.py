"""Scenario files and --set/--option/--fault: one builder, errors with file:line."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.errors import ConfigError, RtupollError, UsageError
from rtupoll.sim.engine import Engine
from rtupoll.sim.scenario import DEFAULT_DEVICES, build

EXAMPLE = """\
seed: 7
baudrate: 9600
turnaround: 0.01
devices:
  - device: net-irnet-pro@1
    variant: 0
    values: {concentration: 12.5, warning: [WARMUP_WARNING], error: NO_ERROR}
  - device: huiwen-aq@3
    write_reply: short
    turnaround: 0.05
    faults: [crc@10%]
faults: ["1:dead@5-", stray=0xFF@0.05]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bus.yaml"
    path.write_text(text)
    return path


def test_the_documented_example(tmp_path: Path) -> None:
    c = build(scenario=write(tmp_path, EXAMPLE))
    assert (c.seed, c.baudrate) == (7, 9600)
    irnet, huiwen = c.devices
    assert irnet.name == "net-irnet-pro@1" and irnet.variant == 0
    assert irnet.pins == {"concentration": 12.5, "warning": ["WARMUP_WARNING"],
                          "error": "NO_ERROR"}
    assert (irnet.turnaround, huiwen.turnaround) == (0.01, 0.05)
    assert huiwen.write_reply == "short"
    assert [str(f) for f in huiwen.faults] == ["crc@10%"] and huiwen.faults[0].target == 3
    assert [str(f) for f in irnet.faults] == ["1:dead@5-"]
    assert [str(f) for f in c.faults] == ["stray=0xFF@0.05"]
    d = Engine(c.devices, c.faults, seed=c.seed, tick=None).device(1)
    assert d.value("concentration").value == 12.5 and d.value("error").value == "NO_ERROR"


def test_command_line_wins_and_adds_devices(tmp_path: Path) -> None:
    c = build(["radar-level@2", "huiwen-aq@3"], scenario=write(tmp_path, EXAMPLE), seed=1,
              baudrate=19200, sets=["huiwen-aq@3.co2=800"])
    assert [d.name for d in c.devices] == ["net-irnet-pro@1", "radar-level@2", "huiwen-aq@3"]
    assert (c.seed, c.baudrate) == (1, 19200)
    assert c.devices[2].pins == {"co2": 800} and c.devices[2].write_reply == "short"


def test_no_devices_anywhere_means_one_of_each_seed_profile() -> None:
    assert [d.name for d in build().devices] == list(DEFAULT_DEVICES)


def test_set_values_are_parsed_for_the_field() -> None:
    c = build(["net-irnet-pro@1", "banner-ez-array@5"], sets=[
        "net-irnet-pro@1.warning=WARMUP_WARNING,HW_TEST_WARNING",
        "net-irnet-pro@1.error=0x18",
        "net-irnet-pro@1.serial_number=AB12",
        "net-irnet-pro@1.concentration=1e3",
        "banner-ez-array@5.outputs=none",
        "banner-ez-array@5.measurement_1_mode=TBB",
    ])
    assert c.devices[0].pins == {"warning": ["WARMUP_WARNING", "HW_TEST_WARNING"], "error": 0x18,
                                 "serial_number": "AB12", "concentration": 1000.0}
    assert c.devices[1].pins == {"outputs": [], "measurement_1_mode": "TBB"}


def test_a_sentinel_is_set_by_its_name_and_read_as_it() -> None:
    from rtupoll.sim.device import SimDevice

    c = build(["r4dcb08@1"], sets=["r4dcb08@1.temperature_1=no_sensor"], tick=None)
    assert c.devices[0].pins == {"temperature_1": "NO_SENSOR"}
    got = SimDevice(c.devices[0]).value("temperature_1")
    assert got.sentinel is not None and got.sentinel.name == "NO_SENSOR"
    with pytest.raises(UsageError, match=r"'hot' is not a number nor one of its sentinels "
                                         r"\(NO_SENSOR\)"):
        build(["r4dcb08@1"], sets=["r4dcb08@1.temperature_1=hot"])


@pytest.mark.parametrize(("args", "message"), [
    ({"sets": ["huiwen-aq@9.co2=1"]}, "no device huiwen-aq@9 on the simulated bus"),
    ({"sets": ["huiwen-aq@3.cox=1"]}, "has no field 'cox'"),
    ({"sets": ["huiwen-aq@3.co2=lots"]}, "'lots' is not a number"),
    ({"sets": ["huiwen-aq@3.co2=70000"]}, "outside u16"),
    ({"sets": ["huiwen-aq@3.pm25_level=BAD"]}, "'BAD' is not one of"),
    ({"sets": ["huiwen-aq@3co2=1"]}, "is not PROFILE@ADDRESS.NAME=VALUE"),
    ({"options": ["huiwen-aq@3.variant=1"]}, "huiwen-aq has no variants"),
    ({"options": ["huiwen-aq@3.write_reply=maybe"]}, "not one of: echo, short, none"),
    ({"options": ["huiwen-aq@3.speed=1"]}, "unknown device option 'speed'"),
    ({"faults": ["4:dead"]}, "no device at 4"),
])
def test_command_line_mistakes_are_one_line_errors(args: dict[str, list[str]],
                                                   message: str) -> None:
    with pytest.raises(RtupollError, match=message):
        build(["huiwen-aq@3"], **args)  # type: ignore[arg-type]


def test_bad_device_specs() -> None:
    with pytest.raises(UsageError, match="not PROFILE@ADDRESS"):
        build(["huiwen-aq"])
    with pytest.raises(UsageError, match=r"outside 1\.\.255"):
        build(["huiwen-aq@0"])
    with pytest.raises(UsageError, match="no profile 'huiwen'"):
        build(["huiwen@3"])
    with pytest.raises(UsageError, match="taken by huiwen-aq@3"):
        build(["huiwen-aq@3", "radar-level@3"])


@pytest.mark.parametrize(("text", "where"), [
    ("devices:\n  - device: huiwen-aq@3\n    valuse: {co2: 1}\n",
     ":3: devices[0].valuse: unknown key (did you mean 'values'?)"),
    ("devices:\n  - device: huiwen-aq@3\n    values:\n      co2: 70000\n",
     ":4: devices[0].values.co2: 70000 is outside u16"),
    ("devices:\n  - device: huiwen-aq@3\n    values: {nope: 1}\n",
     ":3: devices[0].values.nope: huiwen-aq has no field 'nope'"),
    ("devices:\n  - device: huiwen-aq@3\n    faults: [3:deadd]\n",
     ":3: devices[0].faults[0]: fault '3:deadd': unknown kind"),
    ("devices:\n  - device: huiwen-aq@3\n    faults: ['4:dead']\n",
     ":3: devices[0].faults[0]: fault 4:dead names address 4"),
    ("devices:\n  - device: huiwen-aq@3\n    variant: 2\n",
     ":3: devices[0].variant: huiwen-aq has no variants"),
    ("devices:\n  - {device: huiwen-aq@3}\n  - {device: radar-level@3}\n",
     ":3: devices[1].device: address 3 is taken"),
    ("devices:\n  - {device: radar-level@3}\n  - {device: radar-level@3}\n",
     ":3: devices[1].device: address 3 is taken by radar-level@3 (listed twice)"),
    ("faults: ['7:crc']\n", ":1: faults: fault 7:crc: no device at 7"),
    ("seeed: 3\n", ":1: seeed: unknown key (did you mean 'seed'?)"),
    ("devices: [\n", ":2: YAML syntax"),
])
def test_scenario_mistakes_say_file_line_and_path(tmp_path: Path, text: str, where: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        build(scenario=path)
    assert str(info.value).startswith(str(path) + where), str(info.value)


def test_the_scenario_in_the_docs_builds(tmp_path: Path) -> None:
    doc = (Path(__file__).parents[2] / "docs" / "simulator.md").read_text()
    block = doc.split("## Scenario files", 1)[1].split("```yaml\n", 1)[1].split("```", 1)[0]
    c = build(scenario=write(tmp_path, block))
    assert [d.name for d in c.devices] == ["net-irnet-pro@1", "huiwen-aq@3"]
    assert (c.seed, c.baudrate, c.tick) == (7, 9600, 0.5)
    assert [str(f) for f in c.devices[0].faults] == ["1:dead@50-"]


def test_the_readme_scenario_loads_and_does_what_it_says(tmp_path: Path) -> None:
    from rtupoll.sim.runner import simulated_bus

    readme = (Path(__file__).parents[2] / "README.md").read_text()
    text = readme.split("```yaml\nseed: 7", 1)[1].split("```", 1)[0]
    path = tmp_path / "bus.yaml"
    path.write_text("seed: 7" + text)
    with simulated_bus(scenario=path) as sim:
        assert sim.addresses() == {"net-irnet-pro@1": 1, "huiwen-aq@3": 3}
        assert sim.get(1, "concentration").value == 12.5
        assert sim.get(1, "warning").value == ["WARMUP_WARNING"]
        assert sim.device(1).variant == 0
        assert sim.framing is not None and sim.framing.baudrate == 9600


@pytest.mark.parametrize("devices", [["radar-level@1", "radar-level@1"],
                                     ["huiwen-aq@3", "radar-level@3"]])
def test_two_devices_at_one_address_are_refused_as_the_collision_they_are(
        devices: list[str]) -> None:
    from cli_runner import rtupoll

    for command in (["simulate", *devices], ["poll", "--simulate", "--once", *devices]):
        run = rtupoll(*command)
        assert run.returncode == 2, run
        line, = run.stderr.splitlines()
        assert line.startswith(f"rtupoll: address {devices[0].split('@')[1]} is taken by "
                               f"{devices[0]}") and "collide on a real bus" in line
