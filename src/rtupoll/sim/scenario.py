"""What a simulated bus holds: devices, pinned values, options and faults.

One builder serves the command line, scenario files and tests, so ``--set``, ``--option``
and ``--fault`` mean exactly what the same lines in a scenario mean. A scenario is YAML
read through ``yamlsrc``, so a mistake is reported as ``file:line: path: message``::

    seed: 7                    # optional; the command line's --seed wins
    baudrate: 9600             # optional wire timing; --baud wins
    turnaround: 0.01           # optional, seconds, every device without its own
    devices:
      - device: net-irnet-pro@1
        variant: 0             # data structure 0: 0x0400 answers exception 02
        values: {concentration: 12.5, warning: [WARMUP_WARNING], error: NO_ERROR}
      - device: huiwen-aq@3
        write_reply: short     # the manual's non-echo FC06 reply
        faults: [crc@10%]      # this device's faults (no address needed)
    faults: ["1:dead@50-", stray=0xFF@0.05]

Devices named on the command line are added to the scenario's; a device in both is one
device. With no device anywhere, the bus holds ``DEFAULT_DEVICES``.

A real RS-485 line runs at one speed, and not every device runs at every speed (the
CO2Meter board only at 115200, the IRNET not at 115200). ``split_lines`` puts devices on
as few lines as can exist: the speed most of them run at first, then the rest, so the
default demo is two lines (9600 and 115200), each answering only at its own speed.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rtupoll.config.library import load_one
from rtupoll.config.yamlsrc import Node, load
from rtupoll.errors import ConfigError, RtupollError, UsageError
from rtupoll.model.codec import Value
from rtupoll.model.interpret import field_words
from rtupoll.model.profile import Field, Profile
from rtupoll.sim.device import WRITE_REPLIES, SimDeviceConfig
from rtupoll.sim.faults import Fault, parse_fault

# One of each bundled profile at distinct addresses; co2meter-an117 also answers 0xFE.
DEFAULT_DEVICES = ("net-irnet-pro@1", "radar-level@2", "huiwen-aq@3", "co2meter-an117@4",
                   "banner-ez-array@5")
OPTIONS = ("variant", "write_reply", "turnaround")


# Baud rates in the order people meet them, to break ties between equally good speeds.
COMMON_RATES = (9600, 19200, 38400, 115200, 57600, 4800, 2400, 1200)


@dataclass(frozen=True)
class Scenario:
    devices: tuple[SimDeviceConfig, ...]
    faults: tuple[Fault, ...] = ()  # bus-wide faults (a device's own sit in its config)
    baudrate: int | None = None  # wire timing at this rate (and the line's speed)
    seed: int = 0
    tick: float | None = 1.0  # seconds per value step; None: values never move
    speed: int | None = None  # without timing: the only speed the line answers at

    @property
    def line_speed(self) -> int | None:
        """The speed a client must open the line at (None: any speed)."""
        return self.baudrate or self.speed


def speeds(p: Profile) -> tuple[int, ...]:
    """Every baud rate a profile's device can run at."""
    return p.serial.baudrates or (p.serial.baudrate,)


def split_lines(config: Scenario, prefer: int | None = None) -> tuple[Scenario, ...]:
    """The devices on as few lines as could exist, each line at one speed (and parity).

    Each round takes the speed most remaining devices run at (``prefer`` when any of
    them runs at it; ties: more devices' default, then the more common rate) and puts
    every device that runs at it on one line. Bus-wide faults go to every line. A line
    gets wire timing at its speed when ``config`` has timing (``baudrate``), else it
    only answers clients at its speed (``speed``).
    """
    left = list(config.devices)
    out: list[Scenario] = []
    while left:
        counts: dict[tuple[int, str, int], tuple[int, int]] = {}
        for d in left:
            s = d.profile.serial
            for r in speeds(d.profile):
                n, dflt = counts.get((r, s.parity, s.stopbits), (0, 0))
                counts[(r, s.parity, s.stopbits)] = (n + 1, dflt + (r == s.baudrate))

        def rank(k: tuple[int, str, int], counts: dict[tuple[int, str, int], tuple[int, int]]
                 = counts) -> tuple[int, int, int, int]:
            common = COMMON_RATES.index(k[0]) if k[0] in COMMON_RATES else len(COMMON_RATES)
            return (k[0] == prefer, counts[k][0], counts[k][1], -common)

        rate, parity, stop = max(counts, key=rank)
        here = [d for d in left if rate in speeds(d.profile)
                and (d.profile.serial.parity, d.profile.serial.stopbits) == (parity, stop)]
        left = [d for d in left if d not in here]
        timed = config.baudrate is not None
        out.append(dataclasses.replace(config, devices=tuple(here),
                                       baudrate=rate if timed else None,
                                       speed=None if timed else rate))
    return tuple(out)


def cannot_run(config: Scenario) -> list[str]:
    """Devices on a line whose speed their profile does not list: a bus that cannot exist."""
    rate = config.line_speed
    if rate is None:
        return []
    return [f"{d.name} runs at {', '.join(map(str, speeds(d.profile)))} only, not {rate}"
            for d in config.devices if rate not in speeds(d.profile)]


_CACHE: dict[tuple[str, tuple[str, ...], str], Profile] = {}


def profile(pid: str, dirs: Iterable[Path] = ()) -> Profile:
    """A profile by id, cached: tests and ``poll --simulate`` start many buses."""
    d = tuple(str(p) for p in dirs)
    key = (pid, d, os.environ.get("RTUPOLL_PROFILES", ""))
    if key not in _CACHE:
        _CACHE[key] = load_one(pid, [Path(p) for p in d])
    return _CACHE[key]


def parse_device(text: str) -> tuple[str, int]:
    """``PROFILE@ADDRESS`` -> (profile id, address 1..255)."""
    pid, sep, addr = str(text).strip().rpartition("@")
    if not sep or not pid:
        raise UsageError(f"{text!r} is not PROFILE@ADDRESS (e.g. net-irnet-pro@1)")
    try:
        address = int(addr, 0)
    except ValueError:
        raise UsageError(f"{addr!r} in {text!r} is not an address (1-255)") from None
    if not 1 <= address <= 255:
        raise UsageError(f"address {address} in {text!r} is outside 1..255")
    return pid, address


def parse_value(field: Field, text: str) -> Value:
    """Command-line text -> a value ``field_words`` accepts (numbers, names, flag lists,
    a sentinel's name)."""
    t = text.strip()
    if field.layout.type.value == "string":
        return text
    if field.flags and not t[:1].isdigit():
        return [n.strip() for n in t.split(",") if n.strip() and n.strip() != "none"]
    for conv in (lambda s: int(s, 0), float):
        try:
            return conv(t)
        except ValueError:
            pass
    if field.enum:
        return t
    sentinels = {c.name.lower(): c.name for c in field.sentinels.values()}
    if t.lower() in sentinels:  # what the device says instead of a value: NO_SENSOR
        return sentinels[t.lower()]
    names = f" nor one of its sentinels ({', '.join(sentinels.values())})" if sentinels else ""
    raise UsageError(f"{field.name}: {text!r} is not a number{names}")


def _checked(cfg: SimDeviceConfig, name: str, value: Value) -> Value:
    f = cfg.profile.field(name)
    try:
        field_words(f, value)  # raises EncodeError (a RefusedError) if it cannot be encoded
    except (ValueError, OverflowError):  # NaN or infinity for a scaled integer field
        raise UsageError(f"{name}: {value!r} cannot be stored as {f.layout.type.value}") from None
    return value


def _option(cfg: SimDeviceConfig, name: str, value: object) -> SimDeviceConfig:
    if name == "variant":
        if cfg.profile.variant is None:
            raise UsageError(f"{cfg.profile.id} has no variants")
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
            raise UsageError(f"variant must be a whole number 0..255, not {value!r}")
        return dataclasses.replace(cfg, variant=value)
    if name == "write_reply":
        if value not in WRITE_REPLIES:
            raise UsageError(f"write_reply {value!r} is not one of: {', '.join(WRITE_REPLIES)}")
        return dataclasses.replace(cfg, write_reply=str(value))
    if name == "turnaround":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 10:
            raise UsageError(f"turnaround must be seconds (0..10), not {value!r}")
        return dataclasses.replace(cfg, turnaround=float(value))
    raise UsageError(f"unknown device option {name!r}; options: {', '.join(OPTIONS)}")


def _split_assignment(text: str, what: str) -> tuple[str, str, str]:
    """``PROFILE@ADDR.NAME=VALUE`` -> (device, name, value text)."""
    left, eq, value = text.partition("=")
    device, dot, name = left.rpartition(".")
    if not eq or not dot or "@" not in device:
        raise UsageError(f"{what} {text!r} is not PROFILE@ADDRESS.NAME=VALUE "
                         "(e.g. huiwen-aq@3.co2=800)")
    return device.strip(), name.strip(), value


class _Builder:
    def __init__(self, dirs: Iterable[Path]) -> None:
        self.dirs = tuple(dirs)
        self.devices: dict[int, SimDeviceConfig] = {}
        self.listed: set[int] = set()  # the addresses of the list being read

    def add(self, spec: str, node: Node | None = None) -> SimDeviceConfig:
        pid, address = parse_device(spec)
        p = profile(pid, self.dirs)
        have = self.devices.get(address)
        # the same device named again (the command line adds to a scenario) is that device;
        # another at its address, or one listed twice in one list, would collide
        if have is not None and (have.profile.id != p.id or address in self.listed):
            msg = (f"address {address} is taken by {have.name}"
                   + (" (listed twice)" if have.profile.id == p.id else "")
                   + ": two devices at one address collide on a real bus (both reply, "
                   "the master hears garbage); give each its own address")
            raise node.fail(msg) if node else UsageError(msg)
        self.listed.add(address)
        if have is None:
            self.devices[address] = SimDeviceConfig(p, address)
        return self.devices[address]

    def find(self, spec: str) -> SimDeviceConfig:
        pid, address = parse_device(spec)
        cfg = self.devices.get(address)
        if cfg is None or pid not in (cfg.profile.id, cfg.profile.path):
            have = ", ".join(c.name for c in self.devices.values())
            raise UsageError(f"no device {spec} on the simulated bus (devices: {have})")
        return cfg

    def pin(self, cfg: SimDeviceConfig, name: str, value: Value) -> None:
        value = _checked(cfg, name, value)
        self.devices[cfg.address] = dataclasses.replace(cfg, pins={**cfg.pins, name: value})

    def fault(self, fault: Fault, cfg: SimDeviceConfig | None = None) -> Fault | None:
        """Attach a device fault to its device; returns bus-wide faults unchanged."""
        if cfg is not None:
            if fault.target not in (None, cfg.address):
                raise UsageError(f"fault {fault} names address {fault.target}, "
                                 f"but belongs to {cfg.name}")
            fault = dataclasses.replace(fault, target=cfg.address)
        if fault.target is None:
            return fault
        target = self.devices.get(fault.target)
        if target is None:
            have = ", ".join(c.name for c in self.devices.values())
            raise UsageError(f"fault {fault}: no device at {fault.target} (devices: {have})")
        self.devices[target.address] = dataclasses.replace(target,
                                                           faults=(*target.faults, fault))
        return None


def build(devices: Sequence[str] = (), *, scenario: str | Path | None = None,
          sets: Sequence[str] = (), options: Sequence[str] = (), faults: Sequence[str] = (),
          seed: int | None = None, baudrate: int | None = None, turnaround: float | None = None,
          tick: float | None = 1.0, profile_dirs: Iterable[Path] = ()) -> Scenario:
    """Devices, scenario file and command-line settings -> one validated Scenario."""
    b = _Builder(profile_dirs)
    bus_faults: list[Fault] = []
    top: dict[str, Node] = {}
    if scenario is not None:
        top = load(Path(scenario), ConfigError).mapping(
            {"seed", "baudrate", "turnaround", "tick", "devices", "faults"})
        for dnode in top["devices"].sequence() if "devices" in top else []:
            _scenario_device(b, dnode)
    b.listed.clear()  # the command line may name the scenario's devices again
    for spec in devices:
        b.add(str(spec))
    if not b.devices:
        for spec in DEFAULT_DEVICES:
            b.add(spec)
    for spec in (n.text() for n in top["faults"].sequence()) if "faults" in top else ():
        try:
            f = b.fault(parse_fault(spec))
        except UsageError as exc:
            raise top["faults"].fail(str(exc)) from None
        bus_faults += [f] if f else []
    for text in sets:
        dev, name, value = _split_assignment(text, "--set")
        cfg = b.find(dev)
        b.pin(cfg, name, parse_value(cfg.profile.field(name), value))
    for text in options:
        dev, name, value = _split_assignment(text, "--option")
        cfg = b.find(dev)
        b.devices[cfg.address] = _option(cfg, name, _option_value(value))
    for spec in faults:
        f = b.fault(parse_fault(spec))
        bus_faults += [f] if f else []
    if turnaround is None and "turnaround" in top:
        turnaround = top["turnaround"].number()
        if not 0 <= turnaround <= 10:
            raise top["turnaround"].fail(f"{turnaround:g} s is outside 0..10 s")
    if turnaround is not None:
        for a, cfg in b.devices.items():
            if cfg.turnaround is None:
                b.devices[a] = _option(cfg, "turnaround", turnaround)
    if seed is None:
        seed = top["seed"].integer() if "seed" in top else 0
    if baudrate is None and "baudrate" in top:
        baudrate = top["baudrate"].integer(300, 4_000_000)
    if "tick" in top:
        tick = top["tick"].number()
        if not 0 <= tick <= 3600:
            raise top["tick"].fail(f"{tick:g} s is outside 0..3600 s (0 freezes values)")
        tick = tick or None
    return Scenario(tuple(b.devices[a] for a in sorted(b.devices)), tuple(bus_faults),
                     baudrate, seed, tick)


def _option_value(text: str) -> object:
    for conv in (lambda s: int(s, 0), float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def _scenario_device(b: _Builder, node: Node) -> None:
    m = node.mapping({"device", "values", "faults", *OPTIONS}, {"device"})
    try:
        cfg = b.add(m["device"].text(), m["device"])
    except UsageError as exc:
        raise m["device"].fail(str(exc)) from None
    for name in OPTIONS:
        if name in m:
            try:
                cfg = _option(cfg, name, m[name].value())
            except UsageError as exc:
                raise m[name].fail(str(exc)) from None
    b.devices[cfg.address] = cfg
    for knode, vnode in m["values"].items() if "values" in m else ():
        try:
            b.pin(b.devices[cfg.address], knode.text(), _yaml_value(vnode))
        except RtupollError as exc:
            raise vnode.fail(str(exc)) from None
    for fnode in m["faults"].sequence() if "faults" in m else ():
        try:
            b.fault(parse_fault(fnode.text()), b.devices[cfg.address])
        except UsageError as exc:
            raise fnode.fail(str(exc)) from None


def _yaml_value(node: Node) -> Value:
    if node.is_list:
        return [n.text() for n in node.sequence()]
    v: Any = node.value()
    if isinstance(v, (bool, int, float, str)):
        return v
    raise node.fail(f"expected a number, a name or a list of flag names, got {v!r}")
