"""Site configuration: which buses exist and which devices sit on each.

A site file (format: docs/polling.md) is validated like a profile, every error as
``file:line: path: message``. Beyond the shape, it checks what only makes sense
for a whole bus, because those mistakes cost a day on site: two devices at one
address, a device that cannot run at the bus's serial settings, an "any device"
address (0xFE) on a shared bus, and addresses a device's profile reserves.

The same model is built from ad-hoc command-line devices (``from_specs``), with
the same checks, so ``poll --port P a@1 b@2`` and ``poll --config`` agree.
Pure: reads files, opens no port, imports no pymodbus.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from rtupoll.config.gateway_settings import ServeConfig
from rtupoll.config.gateway_settings import from_node as serve_from_node
from rtupoll.config.http_settings import HttpSettings
from rtupoll.config.http_settings import from_node as http_from_node
from rtupoll.config.idle_gap import idle_gap
from rtupoll.config.library import load_one, note_use
from rtupoll.config.listen import host_port
from rtupoll.config.mqtt_settings import MqttSettings
from rtupoll.config.mqtt_settings import parse_section as parse_mqtt
from rtupoll.errors import ConfigError, RefusedError, RtupollError, UsageError
from rtupoll.frozen import frozen
from rtupoll.io.port_names import gateway
from rtupoll.model.planner import plan
from rtupoll.model.profile import Addressing, Field, Poll, Profile
from rtupoll.rtu import Framing

if TYPE_CHECKING:  # the YAML parser: only when a site file is read
    from rtupoll.config.yamlsrc import Node

DEFAULT_INTERVAL = 1.0  # seconds between scans of a device
# the serial defaults of a bus with no devices (only served to gateway clients)
_NO_DEVICE = Profile(id="(no device)", vendor="", model="", manual="",
                     addressing=Addressing.PDU, fields=())

T = TypeVar("T")
Fail = Callable[[str, str], RtupollError]  # (key, message) -> the error to raise


@frozen
class DeviceConfig:
    """One device to poll: a profile at an address, what to read and how often."""

    name: str
    profile: Profile
    address: int
    fields: tuple[Field, ...]
    interval: float = DEFAULT_INTERVAL
    timeout: float | None = None  # None: the profile's
    retries: int | None = None  # None: the profile's
    line: int = 0
    timeout_ceiling: float | None = None  # the longest timeout learned (None: the default)
    idle_gap: float | None = None  # silence it needs before a request (None: the profile's)

    @property
    def spec(self) -> str:
        return f"{self.profile.id}@{self.address}"

    @property
    def response_timeout(self) -> float:
        return self.profile.limits.timeout if self.timeout is None else self.timeout

    @property
    def retry_count(self) -> int:
        return self.profile.limits.retries if self.retries is None else self.retries

    @functools.cached_property  # (asked before every transaction: computed once)
    def gap(self) -> float:
        """The silence the device needs on the line before a request (``Line.set_idle_gap``)."""
        return self.profile.limits.idle_gap if self.idle_gap is None else self.idle_gap


@frozen
class BusConfig:
    """One RS-485 line (a serial port or an RTU-over-TCP gateway) and its devices."""

    name: str
    port: str
    baudrate: int
    parity: str = "N"
    bytesize: int = 8
    stopbits: int = 1
    devices: tuple[DeviceConfig, ...] = ()
    line: int = 0
    serve: ServeConfig | None = None  # Modbus TCP served to other masters (rtupoll.gateway)
    echo: bool = False  # the adapter echoes each request (``echo: true``, --echo)
    rs485: tuple[float, float] | None = None  # RTS direction control: (before, after) s
    idle_gap: float = 0.0  # silence every device on it gets before a request, seconds

    @property
    def deassert_dtr(self) -> bool:
        """Open with DTR/RTS deasserted when any device on the line asks for it."""
        return any(d.profile.serial.deassert_dtr for d in self.devices)

    @property
    def framing(self) -> Framing:
        return Framing(self.baudrate, self.bytesize, self.parity, self.stopbits)

    @property
    def serial_text(self) -> str:
        return f"{self.baudrate} {self.bytesize}{self.parity}{self.stopbits}"


@frozen
class Site:
    buses: tuple[BusConfig, ...]
    source: str = "command line"
    metrics: str = ""  # HOST:PORT to serve Prometheus metrics on ("": none)
    mqtt: MqttSettings | None = None  # the site file's mqtt: section (docs/mqtt.md)
    http: HttpSettings | None = None  # the site file's http: section (docs/web.md)

    def devices(self) -> Iterator[tuple[BusConfig, DeviceConfig]]:
        for bus in self.buses:
            for dev in bus.devices:
                yield bus, dev


# ---------------------------------------------------------------------------
# the site file

_TOP_KEYS = {"profiles", "buses", "metrics", "mqtt", "http"}
_BUS_KEYS = {"name", "port", "baudrate", "parity", "bytesize", "stopbits", "devices",
             "echo", "rs485", "idle_gap",
             "serve"}
_DEVICE_KEYS = {"name", "profile", "address", "interval", "fields", "timeout", "retries",
                "timeout_ceiling", "idle_gap"}


def load_site(path: Path, profile_dirs: Sequence[Path] = ()) -> Site:
    """Read and check a site file. ``profile_dirs`` (from --profiles) come first."""
    from rtupoll.config.yamlsrc import load

    root = load(path, ConfigError)
    top = root.mapping(_TOP_KEYS, {"buses"})
    extra = list(profile_dirs)
    if "profiles" in top:
        for node in top["profiles"].sequence():
            directory = (path.parent / node.text()).resolve()
            if not directory.is_dir():
                raise node.fail(f"profile directory {directory} does not exist")
            extra.append(directory)
    bus_nodes = top["buses"].sequence()
    if not bus_nodes:
        raise top["buses"].fail("no buses: a site needs at least one")
    buses = [_bus(n, extra) for n in bus_nodes]
    names: dict[str, int] = {}
    ports: dict[str, BusConfig] = {}
    for node, bus in zip(bus_nodes, buses, strict=True):
        m = node.mapping()
        if bus.name in names:
            raise (m.get("name") or m["port"]).fail(
                f"bus name {bus.name!r} is already used at line {names[bus.name]}")
        names[bus.name] = bus.line
        if bus.port in ports:
            other = ports[bus.port]
            raise m["port"].fail(f"port {bus.port} is already used by bus {other.name!r} "
                                 f"(line {other.line}); put all its devices on one bus")
        ports[bus.port] = bus
    seen: dict[str, DeviceConfig] = {}
    for node, bus in zip(bus_nodes, buses, strict=True):
        bm = node.mapping()
        dnodes = bm["devices"].sequence() if "devices" in bm else []
        for dnode, dev in zip(dnodes, bus.devices, strict=True):
            if dev.name in seen:
                raise (dnode.mapping().get("name") or dnode).fail(
                    f"device name {dev.name!r} is already used at line {seen[dev.name].line}")
            seen[dev.name] = dev
    metrics = _listen(top["metrics"]) if "metrics" in top else ""
    mqtt = parse_mqtt(top["mqtt"], path, seen) if "mqtt" in top else None
    http = http_from_node(top["http"]) if "http" in top else None
    return Site(tuple(buses), source=str(path), metrics=metrics, mqtt=mqtt, http=http)


def _listen(node: Node) -> str:
    """``metrics: [HOST:]PORT`` (a port alone: loopback, as ``--metrics``)."""
    text = node.text().strip()
    if host_port(text) is None:  # as --metrics
        raise node.fail(f"{text!r}: expected [HOST:]PORT, e.g. 127.0.0.1:9464")
    return text


def _bus(node: Node, extra: Sequence[Path]) -> BusConfig:
    m = node.mapping(_BUS_KEYS, {"port"} if "serve" in node.mapping() else {"port", "devices"})
    port = _port(m["port"])
    dnodes = m["devices"].sequence() if "devices" in m else []
    if not dnodes and "serve" not in m:
        raise m["devices"].fail("no devices: a bus needs at least one")
    devices = tuple(_device(n, extra) for n in dnodes)
    profiles = [d.profile for d in devices] or [_NO_DEVICE]  # a pure gateway: 9600 8N1
    fail = (m.get("baudrate") or m["port"]).fail
    serial: dict[str, int | str] = {
        "baudrate": m["baudrate"].integer(300, 4_000_000) if "baudrate" in m else
        _common(profiles, "baud rate", lambda p: p.serial.baudrate, fail, "set baudrate"),
        "parity": m["parity"].choice(_parity, ["N", "E", "O"]) if "parity" in m else
        _common(profiles, "parity", lambda p: p.serial.parity, fail, "set parity"),
        "bytesize": m["bytesize"].integer(7, 8) if "bytesize" in m else
        _common(profiles, "byte size", lambda p: p.serial.bytesize, fail, "set bytesize"),
        "stopbits": m["stopbits"].integer(1, 2) if "stopbits" in m else
        _common(profiles, "stop bits", lambda p: p.serial.stopbits, fail, "set stopbits"),
    }
    bus = BusConfig(name=m["name"].text() if "name" in m else port, port=port,
                    baudrate=int(serial["baudrate"]), parity=str(serial["parity"]),
                    bytesize=int(serial["bytesize"]), stopbits=int(serial["stopbits"]),
                    devices=devices, line=node.line,
                    serve=serve_from_node(m["serve"]) if "serve" in m else None,
                    echo=m["echo"].flag() if "echo" in m else False,
                    rs485=_rs485(m["rs485"]) if "rs485" in m else None,
                    idle_gap=idle_gap(m["idle_gap"]) if "idle_gap" in m else 0.0)

    def fail_at(dnode: Node) -> Fail:
        dm = dnode.mapping()
        return lambda key, msg: (dm.get(key) or dnode).fail(msg)

    check_bus(bus, [fail_at(n) for n in dnodes],
              {k: f"at line {m[k].line}" for k in serial if k in m})
    return bus


def _rs485(node: Node) -> tuple[float, float] | None:
    """``rs485: true`` or ``rs485: {delay_before: S, delay_after: S}`` (seconds)."""
    if not node.is_mapping:
        return (0.0, 0.0) if node.flag() else None
    m = node.mapping({"delay_before", "delay_after"})
    delays = []
    for key in ("delay_before", "delay_after"):
        value = m[key].number() if key in m else 0.0
        if not 0 <= value <= 1:
            raise m[key].fail(f"{key} is in seconds, 0..1")
        delays.append(value)
    return delays[0], delays[1]


def _port(node: Node) -> str:
    port = node.text().strip()
    if not port:
        raise node.fail("the port is empty")
    try:
        gateway(port)  # the bus's own reading of tcp://HOST:PORT
    except UsageError as exc:
        raise node.fail(str(exc)) from None
    return port


def _device(node: Node, extra: Sequence[Path]) -> DeviceConfig:
    m = node.mapping(_DEVICE_KEYS, {"profile", "address"})
    pnode = m["profile"]
    pid = pnode.text()
    if pid.endswith((".yaml", ".yml")):  # a file: from the site file's folder, like profiles:
        file = Path(pnode.file).parent / pid
        if not file.is_file():
            raise pnode.fail(f"no profile file {file}")
        pid = str(file)
    try:
        profile = note_use(load_one(pid, extra))
    except UsageError as exc:  # unknown id; a broken profile file keeps its own file:line
        raise pnode.fail(str(exc)) from None
    address = m["address"].integer(0, 255)
    interval = m["interval"].number() if "interval" in m else DEFAULT_INTERVAL
    if not 0 <= interval <= 86_400:
        raise m["interval"].fail(f"{interval:g} s is outside 0..86400 s "
                                 "(0: as fast as the bus allows)")
    timeout = m["timeout"].number() if "timeout" in m else None
    if timeout is not None and not 0.01 <= timeout <= 30:
        raise m["timeout"].fail(f"{timeout:g} s is outside 0.01..30 s")
    retries = m["retries"].integer(0, 10) if "retries" in m else None
    ceiling = m["timeout_ceiling"].number() if "timeout_ceiling" in m else None
    if ceiling is not None and not 0.05 <= ceiling <= 30:
        raise m["timeout_ceiling"].fail(f"{ceiling:g} s is outside 0.05..30 s")
    if "fields" in m:
        fnodes = m["fields"].sequence()
        if not fnodes:
            raise m["fields"].fail("an empty list; leave 'fields' out to poll the default set")
        fields = tuple(_field(profile, n.text(), n.fail) for n in fnodes)
        for i, f in enumerate(fields):
            if f in fields[:i]:
                raise fnodes[i].fail(f"{f.name} is listed twice")
    else:
        fields = profile.default_fields()
    _plannable(profile, fields, (m.get("fields") or pnode).fail)
    name = m["name"].text() if "name" in m else f"{profile.id}@{address}"
    if not name.strip():  # its MQTT topics would have an empty level (plant//availability)
        raise m["name"].fail("the device name is empty: give it a name, or leave 'name' out "
                             "for PROFILE@ADDRESS")
    return DeviceConfig(name, profile, address, fields, interval, timeout, retries, node.line,
                        ceiling, idle_gap(m["idle_gap"]) if "idle_gap" in m else None)


def _field(profile: Profile, name: str, fail: Callable[[str], RtupollError]) -> Field:
    for f in profile.fields:
        if f.name == name:
            if f.poll is Poll.NEVER:
                raise fail(f"{name} is never polled: reading it has side effects "
                           f"({f.description or 'see the profile'}); use 'rtupoll read'")
            return f
    from rtupoll.model.names import close_names

    hint = close_names(name, profile.names())
    raise fail(f"{profile.id} has no field {name!r}"
               + (f" (did you mean {hint[0]!r}?)" if hint else ""))


def _plannable(profile: Profile, fields: Sequence[Field],
               fail: Callable[[str], RtupollError]) -> None:
    """Refuse fields no request can read (an unsupported function, a too-wide field)."""
    try:
        plan(fields, profile)
    except RefusedError as exc:
        raise fail(str(exc)) from None


def _common(profiles: Sequence[Profile], what: str, get: Callable[[Profile], T],
            fail: Callable[[str], RtupollError], fix: str) -> T:
    """A serial setting all the devices' profiles agree on, or an error saying how to fix it."""
    values = {get(p): p.id for p in profiles}
    if len(values) > 1:
        listed = ", ".join(f"{v} ({pid})" for v, pid in values.items())
        raise fail(f"the devices' profiles disagree on the {what} ({listed}); {fix} for the bus")
    return next(iter(values))


def _parity(text: str) -> str:
    if text.upper() not in ("N", "E", "O"):
        raise ValueError(text)
    return text.upper()


# ---------------------------------------------------------------------------
# checks that need the whole bus


def check_bus(bus: BusConfig, fails: Sequence[Fail], set_by: dict[str, str]) -> None:
    """Refuse a bus that cannot work; ``fails[i]`` places an error on device i.

    ``set_by`` says where each serial setting given explicitly came from (``at
    line 4``, ``by --baudrate``), so a contradiction names both sides.
    """
    devices = bus.devices
    for i, dev in enumerate(devices):
        fail, p, addr = fails[i], dev.profile, dev.address
        shared = len(devices) > 1
        if addr == p.addresses.any:
            if shared:
                raise fail("address", f"{addr} (0x{addr:02X}) is the 'any device' address of "
                           f"{p.id}: every such device answers it, so it only works alone on a "
                           f"bus, and {bus.name} has {len(devices)} devices")
        else:
            why = p.addresses.check(addr)
            if why:
                raise fail("address", why)
        for other in devices[:i]:
            if other.address == addr:
                raise fail("address", f"address {addr} is already used by {other.name}"
                           + (f" (line {other.line})" if other.line else ""))
        for other in devices:
            oa = other.profile.addresses
            if other is dev or other.profile.id == p.id:
                continue
            if addr in oa.reserved:
                raise fail("address", f"{addr} (0x{addr:02X}) is reserved on a bus with "
                           f"{other.name}: {oa.reserved[addr]}")
            if addr == oa.any:
                raise fail("address", f"{other.name} also answers {addr} (0x{addr:02X}), its "
                           "'any device' address, so the replies would collide")
        _check_serial(bus, dev, fail, set_by)


def _check_serial(bus: BusConfig, dev: DeviceConfig, fail: Fail, set_by: dict[str, str]
                  ) -> None:
    s, pid = dev.profile.serial, dev.profile.id

    def origin(key: str) -> str:
        how = set_by.get(key)
        return f" (set {how})" if how else ""

    if bus.baudrate not in s.baudrates:
        raise fail("profile", f"{pid} cannot run at {bus.baudrate} baud, the speed of bus "
                   f"{bus.name}{origin('baudrate')}; it supports "
                   f"{', '.join(map(str, s.baudrates))}")
    for key, mine, theirs, what in (("parity", bus.parity, s.parity, "parity"),
                                    ("bytesize", bus.bytesize, s.bytesize, "data bits"),
                                    ("stopbits", bus.stopbits, s.stopbits, "stop bits")):
        if mine != theirs:
            raise fail("profile", f"{pid} uses {what} {theirs}, bus {bus.name} uses "
                       f"{mine}{origin(key)}")


# ---------------------------------------------------------------------------
# ad-hoc devices from the command line


def from_specs(port: str, specs: Sequence[tuple[str, int]], *, baudrate: int | None = None,
               parity: str | None = None, stopbits: int | None = None,
               interval: float = DEFAULT_INTERVAL, fields: Sequence[str] = (),
               timeout: float | None = None, retries: int | None = None,
               profile_dirs: Sequence[Path] = (), check_serial: bool = True,
               timeout_ceiling: float | None = None, idle_gap: float | None = None) -> Site:
    """One bus from ``--port`` and ``PROFILE@ADDRESS`` arguments, checked like a site file.

    Serial settings not given come from the profiles when they agree. ``fields``
    (from ``--fields``) applies to every device that has such a field; each name
    must exist somewhere and each device must have at least one of them.
    ``check_serial=False`` is for the simulator, which serves any device at any speed.
    ``idle_gap`` (``--idle-gap``) replaces every device's profile's ``limits.idle_gap``.
    """
    if not specs:
        raise UsageError("name at least one device, PROFILE@ADDRESS (e.g. net-irnet-pro@1)")
    profiles = [note_use(load_one(pid, profile_dirs)) for pid, _ in specs]
    names = [f"{p.id}@{a}" for p, (_, a) in zip(profiles, specs, strict=True)]
    wanted = list(dict.fromkeys(fields))
    known = sorted({n for p in profiles for n in p.names()})
    for f in wanted:
        if f not in known:
            from rtupoll.model.names import close_names

            hint = close_names(f, known)
            raise UsageError(f"--fields: no device here has a field {f!r}"
                             + (f" (did you mean {hint[0]!r}?)" if hint else ""))
    chosen: list[tuple[Field, ...]] = []
    for p, name in zip(profiles, names, strict=True):
        if not wanted:
            chosen.append(p.default_fields())
            continue
        have = tuple(_field(p, f, UsageError) for f in wanted if f in p.names())
        if not have:
            raise UsageError(f"{name} has none of the fields {', '.join(wanted)} "
                             f"(its fields: {', '.join(p.names())})")
        _plannable(p, have, UsageError)
        chosen.append(have)
    gateway(port)  # refuses a malformed tcp://HOST:PORT

    bus = BusConfig(
        name=port, port=port,
        baudrate=baudrate or _common(profiles, "baud rate", lambda p: p.serial.baudrate,
                                     UsageError, "give --baudrate"),
        parity=(parity or _common(profiles, "parity", lambda p: p.serial.parity,
                                  UsageError, "give --parity")).upper(),
        bytesize=_common(profiles, "byte size", lambda p: p.serial.bytesize, UsageError,
                         "use a site file"),
        stopbits=stopbits or _common(profiles, "stop bits", lambda p: p.serial.stopbits,
                                     UsageError, "give --stopbits"),
        devices=tuple(DeviceConfig(name, p, a, fs, interval, timeout, retries,
                                   timeout_ceiling=timeout_ceiling, idle_gap=idle_gap)
                      for name, p, (_, a), fs in zip(names, profiles, specs, chosen,
                                                     strict=True)),
    )
    given = {"baudrate": baudrate, "parity": parity, "stopbits": stopbits}
    set_by = {k: f"by --{k}" for k, v in given.items() if v is not None}
    if not check_serial:
        bus = BusConfig(bus.name, bus.port, bus.baudrate, bus.parity, bus.bytesize, bus.stopbits,
                        tuple(_any_speed(d, bus) for d in bus.devices))
    check_bus(bus, [_usage_at(n) for n in names], set_by)
    return Site((bus,))


def _usage_at(name: str) -> Fail:
    return lambda _key, msg: UsageError(f"{name}: {msg}")


def _any_speed(dev: DeviceConfig, bus: BusConfig) -> DeviceConfig:
    """The device as the simulator serves it: at whatever speed the bus runs."""
    serial = replace(dev.profile.serial, baudrate=bus.baudrate,
                     baudrates=(*dev.profile.serial.baudrates, bus.baudrate),
                     parity=bus.parity, bytesize=bus.bytesize, stopbits=bus.stopbits)
    return replace(dev, profile=replace(dev.profile, serial=serial))
