"""Prometheus metrics: ``rtupoll poll --metrics HOST:PORT`` serves ``/metrics``.

A custom collector reads the scheduler's own state at scrape time (each device's
latest cycle and ``DeviceStats``, each bus's ``BusLoad``, the bus's ``BusStats``):
nothing is updated per reading except the latency histogram, which has to count
every transaction. The HTTP server runs on the event loop, so a scrape never
sees a half-updated device. ``prometheus_client`` (the ``metrics`` extra) is
imported only when this runs.

Names (docs/service.md has the list): one gauge per numeric field, named from the
profile's field and unit in base units (``rtupoll_co2_ppm``,
``rtupoll_temperature_celsius`` from kelvin or degrees Celsius alike,
``rtupoll_pm25_grams_per_cubic_meter`` from µg/m³), labelled ``bus`` and ``device``;
a total that only grows (``counter: true`` in the profile: energy) is a counter
(``rtupoll_import_active_energy_joules_total``). Values are rounded to the decimals
the field really has (its precision or scale, and the conversion's), so a K -> °C
conversion gives 23.52, not 23.52000000000004. The HELP text says the field and the
unit of the family, never one profile's description: a family is shared by every
profile with that field. A generic ``rtupoll_reading{field,unit}`` would put
different units under one name, so ``sum`` and ``avg`` over it would mean nothing,
against Prometheus's naming practice; per-field names also make the queries read
as what they measure. A field whose name already carries its unit (the radar's
``level_cm`` and ``level_mm``, one level at two resolutions) keeps its name as it is.
Enums: ``_code`` (the number) and ``_state{state}`` (1 for the current name, 0 for
the other documented ones); flags: ``_flag{flag}``, one series per flag; strings:
``_info{value}``. A reading that failed in the device's latest cycle is not
exported: the series disappears, it never keeps its last value as if fresh. A field
on a slower interval (``interval: 60``) keeps its last good reading between its reads.

``exposition`` renders the text from the state; ``Exporter`` is what a running poll
shows, for the dashboard's ``/metrics`` (``--http``) and for ``MetricsService``, which
serves it on a listener of its own, no aiohttp (``--metrics``: loopback unless a host is
given, as ``--serve``; ``outputs.metrics_listener``).
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rtupoll.config.listen import listen_address
from rtupoll.errors import MissingLibrary, UsageError
from rtupoll.jobs.histogram import Histogram
from rtupoll.jobs.services import Follow, Service
from rtupoll.jobs.stats import State
from rtupoll.model.interpret import number_decimals, places

if TYPE_CHECKING:
    from prometheus_client import CollectorRegistry
    from prometheus_client.core import Metric

    from rtupoll.config.site import Site
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.jobs.services import Reload
    from rtupoll.jobs.stats import Reading
    from rtupoll.model.profile import Field
    from rtupoll.outputs.metrics_listener import MetricsListener

log = logging.getLogger("rtupoll.metrics")

PREFIX = "rtupoll_"
# transaction times on RS-485: a few ms at 115200 baud to a second for a slow device
BUCKETS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)
# profile unit -> (Prometheus unit word, scale, offset): value * scale + offset
UNITS: dict[str, tuple[str, float, float]] = {
    "K": ("celsius", 1.0, -273.15), "°C": ("celsius", 1.0, 0.0), "degC": ("celsius", 1.0, 0.0),
    "m": ("meters", 1.0, 0.0), "cm": ("meters", 0.01, 0.0), "mm": ("meters", 0.001, 0.0),
    "%": ("ratio", 0.01, 0.0), "%RH": ("ratio", 0.01, 0.0),
    "s": ("seconds", 1.0, 0.0), "ms": ("seconds", 0.001, 0.0), "min": ("seconds", 60.0, 0.0),
    "h": ("seconds", 3600.0, 0.0), "d": ("seconds", 86400.0, 0.0),
    "V": ("volts", 1.0, 0.0), "mV": ("volts", 0.001, 0.0),
    "A": ("amperes", 1.0, 0.0), "mA": ("amperes", 0.001, 0.0),
    "W": ("watts", 1.0, 0.0), "kW": ("watts", 1000.0, 0.0),
    "Wh": ("joules", 3600.0, 0.0), "kWh": ("joules", 3.6e6, 0.0),
    "Pa": ("pascals", 1.0, 0.0), "hPa": ("pascals", 100.0, 0.0), "kPa": ("pascals", 1e3, 0.0),
    "bar": ("pascals", 1e5, 0.0), "Hz": ("hertz", 1.0, 0.0),
    "µg/m³": ("grams_per_cubic_meter", 1e-6, 0.0),
    "ug/m3": ("grams_per_cubic_meter", 1e-6, 0.0),
    "mg/m³": ("grams_per_cubic_meter", 1e-3, 0.0),
    "mg/m3": ("grams_per_cubic_meter", 1e-3, 0.0),
    "Ah": ("coulombs", 3600.0, 0.0), "mAh": ("coulombs", 3.6, 0.0),
    "°": ("degrees", 1.0, 0.0),
    "m/s": ("meters_per_second", 1.0, 0.0), "km/h": ("meters_per_second", 1 / 3.6, 0.0),
    "Ω": ("ohms", 1.0, 0.0), "kΩ": ("ohms", 1e3, 0.0), "MΩ": ("ohms", 1e6, 0.0),
    "µS/cm": ("siemens_per_meter", 1e-4, 0.0), "uS/cm": ("siemens_per_meter", 1e-4, 0.0),
    "mS/cm": ("siemens_per_meter", 0.1, 0.0), "S/m": ("siemens_per_meter", 1.0, 0.0),
}
# a unit a field's name spells out (charging_amp_hours_today): dropped from the metric's
# name when the value is converted, which then ends in the base unit instead
SPELLED = {"Ah": "amp_hours", "mAh": "milliamp_hours", "Wh": "watt_hours",
           "kWh": "kilowatt_hours", "h": "hours", "min": "minutes", "d": "days",
           "ms": "milliseconds"}
SIGNIFICANT = 12  # digits kept where a field's decimals are unknown (f32/f64): no float noise


# the collector's own families (and their sample names): no field may take these names
RESERVED = frozenset({
    f"rtupoll_{n}{suffix}" for n in (
        "device_up", "device_state", "device_info", "requests", "exceptions", "cycles",
        "late_replies", "device_timeout_seconds", "attempts", "retried",
        "device_idle_gap_seconds", "last_good_reading_age_seconds",
        "request_duration_seconds", "bus_utilisation_ratio", "bus_transactions",
        "bus_busy_seconds", "bus_port_up", "bus_port_losses")
    for suffix in ("", "_total", "_bucket", "_count", "_sum", "_created")})


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``[v6]:PORT`` or ``:PORT`` (loopback, as ``--serve``) -> (host, port).
    Every interface: ``0.0.0.0:PORT`` (IPv4) or ``[::]:PORT`` (IPv6 and IPv4)."""
    return listen_address(text, "--metrics", "127.0.0.1:9464")


# ---------------------------------------------------------------------------
# naming


def _word(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")


@dataclass(frozen=True)
class FieldMetric:
    """How one profile field is exported: its family name, kind and unit conversion."""

    name: str  # without the kind's suffix (_code, _state, _flag, _info; _total: counters)
    kind: str  # "gauge" | "counter" | "enum" | "flags" | "info"
    help: str
    scale: float = 1.0
    offset: float = 0.0
    decimals: int | None = None  # of the converted value; None: SIGNIFICANT digits

    def convert(self, value: float) -> float:
        x = value * self.scale + self.offset if (self.scale, self.offset) != (1, 0) \
            else float(value)
        if not math.isfinite(x) or x == 0:
            return x
        if self.decimals is not None:
            return round(x, self.decimals)
        return round(x, SIGNIFICANT - 1 - math.floor(math.log10(abs(x))))


def field_metric(f: Field) -> FieldMetric:
    """The metric a profile field becomes (see the module docstring)."""
    base = _word(f.name) or "field"
    what = f"Field {f.name}"
    if f.enum:
        return FieldMetric(PREFIX + base, "enum", what)
    if f.flags:
        return FieldMetric(PREFIX + base, "flags", what)
    if f.layout.type.value == "string":
        return FieldMetric(PREFIX + base, "info", what)
    kind = "counter" if f.counter else "gauge"
    unit = f.unit.strip()
    known = number_decimals(f)
    if unit and base.endswith("_" + _word(unit)):  # level_cm: the name says the unit
        return FieldMetric(PREFIX + base, kind, f"{what}, in {unit}", decimals=known)
    word, scale, offset = UNITS.get(unit, (_word(unit), 1.0, 0.0))
    if f.difference:  # a correction of 1.5 K is one of 1.5 °C: scaled, never offset
        offset = 0.0
    spelled = SPELLED.get(unit)
    if spelled and (scale, offset) != (1, 0) and f"_{spelled}_" in f"_{base}_":
        base = f"_{base}_".replace(f"_{spelled}_", "_").strip("_") or "field"
    name = base if not word or base.endswith("_" + word) else f"{base}_{word}"
    decimals = None if known is None else \
        max(known + (places(scale) if scale < 1 else 0), places(offset))
    # the family's unit only: profiles with other units share the family (K and °C)
    note = f", in {word.replace('_', ' ')}" if word else ""
    return FieldMetric(PREFIX + name, kind, what + note, scale, offset, decimals)


# ---------------------------------------------------------------------------
# what is counted between scrapes


@dataclass
class BusCounters:
    port_losses: int = 0
    port_down: bool = False


# ---------------------------------------------------------------------------
# the collector


class SchedulerCollector:
    """``prometheus_client`` collector over a running ``Scheduler`` (read at scrape time)."""

    def __init__(self, scheduler: Scheduler, *, wall: Callable[[], float] = time.time,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.scheduler = scheduler
        self.wall, self.clock = wall, clock
        self.histograms: dict[str, Histogram] = {}  # device name -> its transaction times
        self.bus_counters: dict[str, BusCounters] = {}  # bus name -> port losses
        self._fields: dict[tuple[str, str], FieldMetric] = {}

    # called by the service per device cycle --------------------------------

    def observe(self, bus: BusPoller, dev: DevicePoller, readings: list[Reading]) -> None:
        self.histograms.setdefault(dev.config.name, Histogram(BUCKETS)).catch_up(
            dev.stats.latencies)
        bc = self.bus_counters.setdefault(bus.config.name, BusCounters())
        down = bool(readings) and all(r.status == "port" for r in readings)
        if down and not bc.port_down:
            bc.port_losses += 1
        bc.port_down = down

    # called by prometheus_client at scrape time ----------------------------

    def collect(self) -> Iterator[Metric]:
        from prometheus_client.core import (
            CounterMetricFamily,
            GaugeMetricFamily,
            HistogramMetricFamily,
        )

        dev_labels = ["bus", "device"]
        up = GaugeMetricFamily("rtupoll_device_up", "1 when the device's last cycle got a valid "
                               "reply; 0 when backed off or never answered", labels=dev_labels)
        state = GaugeMetricFamily("rtupoll_device_state", "The device's state (1 for the "
                                  "current one)", labels=[*dev_labels, "state"])
        info = GaugeMetricFamily("rtupoll_device_info", "The device's profile and address",
                                 labels=[*dev_labels, "profile", "address"])
        requests = CounterMetricFamily("rtupoll_requests", "Transactions by outcome",
                                       labels=[*dev_labels, "outcome"])
        exceptions = CounterMetricFamily("rtupoll_exceptions", "Exception replies by code",
                                         labels=[*dev_labels, "code"])
        cycles = CounterMetricFamily("rtupoll_cycles", "Device cycles (scans)",
                                     labels=dev_labels)
        attempts = CounterMetricFamily("rtupoll_attempts", "Requests put on the wire, retries "
                                       "included, by how each ended (answered, timeout, "
                                       "garbled)", labels=[*dev_labels, "outcome"])
        retried = CounterMetricFamily("rtupoll_retried", "Transactions answered only by a "
                                      "retry (also counted in rtupoll_requests outcome ok)",
                                      labels=dev_labels)
        gap = GaugeMetricFamily("rtupoll_device_idle_gap_seconds", "The silence on the line "
                                "a request to the device waits for (set or learned; absent: "
                                "the 3.5 characters only)", labels=[*dev_labels, "source"])
        late = CounterMetricFamily("rtupoll_late_replies", "Replies that came after their "
                                   "request had timed out (counted, never decoded)",
                                   labels=dev_labels)
        waits = GaugeMetricFamily("rtupoll_device_timeout_seconds", "How long rtupoll waits "
                                  "for the device's reply now (learned, or pinned)",
                                  labels=dev_labels)
        age = GaugeMetricFamily("rtupoll_last_good_reading_age_seconds",
                                "Seconds since the device's last good reading "
                                "(absent when it never answered)", labels=dev_labels)
        latency = HistogramMetricFamily("rtupoll_request_duration_seconds",
                                        "Time of answered transactions", labels=dev_labels)
        bus_labels = ["bus"]
        util = GaugeMetricFamily("rtupoll_bus_utilisation_ratio",
                                 "Share of the last 10 s the bus was busy", labels=bus_labels)
        btx = CounterMetricFamily("rtupoll_bus_transactions", "Transactions on the bus",
                                  labels=bus_labels)
        busy = CounterMetricFamily("rtupoll_bus_busy_seconds",
                                   "Seconds the bus was held (rate() of it: utilisation)",
                                   labels=bus_labels)
        port_up = GaugeMetricFamily("rtupoll_bus_port_up", "1 while the port is open and "
                                    "working; 0 while it is gone (adapter unplugged, gateway "
                                    "down)", labels=bus_labels)
        losses = CounterMetricFamily("rtupoll_bus_port_losses", "Times the port went away",
                                     labels=bus_labels)
        families: dict[str, Metric] = {}
        now, wall = self.clock(), self.wall()
        for bp in self.scheduler.buses:
            b = bp.config.name
            util.add_metric([b], bp.load.utilisation(now))
            btx.add_metric([b], bp.load.transactions)
            stats = bp.transport.stats
            if stats is not None:
                busy.add_metric([b], stats.busy)
            port_up.add_metric([b], 0.0 if bp.port_error else 1.0)
            losses.add_metric([b], self.bus_counters.get(b, BusCounters()).port_losses)
            for dev in bp.devices:
                d, st = dev.config.name, dev.stats
                labels = [b, d]
                up.add_metric(labels, 1.0 if st.state is State.ONLINE else 0.0)
                for s in State:
                    state.add_metric([*labels, s.value], 1.0 if st.state is s else 0.0)
                info.add_metric([*labels, dev.config.profile.id, str(dev.config.address)], 1.0)
                for outcome, n in (("ok", st.ok), ("timeout", st.timeouts),
                                   ("garbled", st.garbled),
                                   ("exception", st.exception_count)):
                    requests.add_metric([*labels, outcome], n)
                for code, n in sorted(st.exceptions.items()):
                    exceptions.add_metric([*labels, f"{code:02d}"], n)
                cycles.add_metric(labels, st.cycles)
                ended = st.timed_out + st.garbled_attempts
                for outcome, n in (("answered", max(0, st.attempts - ended)),
                                   ("timeout", st.timed_out), ("garbled", st.garbled_attempts)):
                    attempts.add_metric([*labels, outcome], n)
                retried.add_metric(labels, st.retried)
                if st.idle_gap:
                    gap.add_metric([*labels, st.gap_source], st.idle_gap)
                late.add_metric(labels, st.late)
                if st.timeout is not None:
                    waits.add_metric(labels, st.timeout)
                if st.last_good_time is not None:
                    age.add_metric(labels, max(0.0, wall - st.last_good_time))
                h = self.histograms.get(d)
                if h is not None:
                    latency.add_metric(labels, h.buckets(), h.sum)
                for r in st.latest.values():
                    if r.value is not None:
                        self._reading(families, labels, dev, r)
        yield from (up, state, info, requests, exceptions, cycles, attempts, retried, late,
                    waits, gap, age, latency, util, btx, busy, port_up, losses)
        yield from families.values()

    def _metric(self, dev: DevicePoller, f: Field) -> FieldMetric:
        k = (dev.config.profile.id, f.name)
        fm = self._fields.get(k)
        if fm is None:
            fm = self._fields[k] = field_metric(f)
        return fm

    def _reading(self, families: dict[str, Metric], labels: list[str], dev: DevicePoller,
                 r: Reading) -> None:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        fv = r.value
        assert fv is not None
        fm = self._metric(dev, r.field)

        def family(suffix: str, extra: tuple[str, ...] = (), help_text: str = "",
                   counter: bool = False) -> Metric:
            name = fm.name + suffix
            if name in RESERVED or name + "_total" in RESERVED:  # a field called device_up
                name += "_value"                                  # must not shadow the real one
            kind = "counter" if counter else "gauge"
            want = ["bus", "device", *extra]
            fam = families.get(name)
            if fam is not None and (fam.type != kind or
                                    (fam.samples and list(fam.samples[0].labels) != want)):
                name = f"{name}_{_word(dev.config.profile.id)}"  # a clash across profiles
                fam = families.get(name)
            if fam is None:
                cls = CounterMetricFamily if counter else GaugeMetricFamily
                fam = families[name] = cls(name, help_text or fm.help, labels=want)
            return fam

        value = fv.output  # None: a sentinel ("not available"), which is no reading
        if value is None:
            return
        if fm.kind == "enum" and fv.code is not None:
            _add(family("_code", help_text=f"{fm.help}: the enum's code"), labels,
                 float(fv.code))
            names = [c.name for c in r.field.enum.values()]
            if isinstance(value, str) and value not in names:
                names.append(value)
            fam = family("_state", ("state",), f"{fm.help}: 1 for the enum's current name")
            for n in names:
                _add(fam, [*labels, n], 1.0 if n == value else 0.0)
        elif fm.kind == "flags" and isinstance(value, list):
            names = [c.name for c in r.field.flags.values()]
            names += [n for n in value if n not in names]
            fam = family("_flag", ("flag",), f"{fm.help}: 1 for each flag set")
            for n in names:
                _add(fam, [*labels, n], 1.0 if n in value else 0.0)
        elif isinstance(value, str):
            _add(family("_info", ("value",), f"{fm.help}: its text, as the value label"),
                 [*labels, value], 1.0)
        elif isinstance(value, (int, float)):
            converted = fm.convert(float(value))
            if math.isfinite(converted):  # a NaN register is no reading
                _add(family("", counter=fm.kind == "counter"), labels, converted)


def _add(fam: Metric, labels: list[str], value: float) -> None:
    fam.add_metric(labels, value)  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------
# the exposition text: state in, text out (no HTTP)


def exposition(registry: CollectorRegistry, accept: str = "") -> tuple[bytes, str]:
    """The ``/metrics`` body for a registry, in the format an ``Accept`` header asks for
    (the text format when it asks for none): ``(body, content type)``. Any HTTP server
    can serve it; ``Exporter.render`` is what both of ``poll``'s listeners serve."""
    from prometheus_client.exposition import choose_encoder

    encoder, ctype = choose_encoder(accept)
    return encoder(registry), ctype


# ---------------------------------------------------------------------------
# what /metrics shows of a running poll, for either listener


class Exporter:
    """The scheduler's collector and the other services' (the gateway's clients) in one
    registry, fed every device cycle: ``render`` is the ``/metrics`` body, served by
    ``MetricsService`` (``--metrics``) and by the dashboard (``--http``) alike."""

    def __init__(self, scheduler: Scheduler, others: Sequence[object] = ()) -> None:
        from prometheus_client import CollectorRegistry

        self.collector = SchedulerCollector(scheduler)
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(self.collector)
        for other in others:
            self.registry.register(other)  # type: ignore[arg-type]
        self._bus_of: dict[str, BusPoller] = {}

    def render(self, accept: str = "") -> tuple[bytes, str]:
        """The exposition now: ``(body, content type)`` (see ``exposition``)."""
        return exposition(self.registry, accept)

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        bus = self._bus_of.get(dev.config.name)
        if bus is None or dev not in bus.devices:  # not seen yet, or moved by a reload
            self.follow(self.collector.scheduler)
            bus = self._bus_of.get(dev.config.name)
        if bus is not None:
            self.collector.observe(bus, dev, readings)

    def follow(self, scheduler: Scheduler) -> None:
        """Which bus each device is on (again, after a reload)."""
        self._bus_of = {d.config.name: bp for bp in scheduler.buses for d in bp.devices}


# ---------------------------------------------------------------------------
# the service: the exporter on its own listener (outputs.metrics_listener)


class MetricsService(Service):
    """Serves ``/metrics`` for the life of ``poll`` (a ``rtupoll.jobs.services.Service``)."""

    def __init__(self, listen: str, others: Sequence[object] = ()) -> None:
        """``others``: other services' collectors (the gateway's clients), served too."""
        self.host, self.port = parse_listen(listen)
        try:
            import prometheus_client  # noqa: F401
        except ImportError:
            raise MissingLibrary("--metrics", "metrics") from None
        self.others: list[Any] = list(others)
        self.exporter: Exporter | None = None
        self._listener: MetricsListener | None = None

    @property
    def address(self) -> str:
        """``http://HOST:PORT/metrics`` once listening, else ""."""
        return self._listener.address if self._listener is not None else ""

    def render(self, accept: str = "") -> tuple[bytes, str]:
        """The exposition now: ``(body, content type)`` (see ``exposition``)."""
        if self.exporter is None:
            raise RuntimeError("the metrics service has not started")
        return self.exporter.render(accept)

    async def start(self, scheduler: Scheduler) -> None:
        from rtupoll.outputs.metrics_listener import MetricsListener

        self.exporter = Exporter(scheduler, self.others)
        listener = MetricsListener(self.host, self.port, self.exporter.render)
        try:
            await listener.start()
        except OSError as exc:
            why = os.strerror(exc.errno) if exc.errno else str(exc)
            raise UsageError(f"--metrics: cannot listen on {self.host}:{self.port}: "
                             f"{why}") from None
        self._listener = listener
        log.info("serving metrics on %s", self.address, extra={"event": "metrics"})

    def on_readings(self, dev: DevicePoller, readings: list[Reading]) -> None:
        if self.exporter is not None:
            self.exporter.on_readings(dev, readings)

    async def on_reload(self, site: Site) -> Reload:
        """Devices may have moved to other buses: which bus each is on, again."""
        def then(scheduler: Scheduler) -> list[str]:
            if self.exporter is not None:
                self.exporter.follow(scheduler)
            return []
        return Follow(then)

    async def stop(self) -> None:
        if self._listener is not None:
            await self._listener.stop()
            self._listener = None
