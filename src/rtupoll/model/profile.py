"""Device profiles: the model of one vendor's register map and quirks.

A profile is one YAML file (format: docs/profiles.md), read and validated by
``rtupoll.config.profile_file`` into these frozen dataclasses. Everything
vendor-specific lives in the YAML; no code here names a device.
"""

from __future__ import annotations

import dataclasses
import enum
import re
from collections.abc import Mapping

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen
from rtupoll.model.codec import ByteOrder, Layout
from rtupoll.model.transforms import Transform
from rtupoll.rtu import Table
from rtupoll.rtu.functions import MAX_REGISTERS

_LINE_SPEED_WORDS = ("baud", "uart", "bitrate")  # field names that set the line speed
MAX_LABEL = 40  # characters in a field's label (docs/profiles.md, "Labels")
_ASIDE = re.compile(r" \(|; ")
# words that make a field's number a difference of its unit, never an absolute value:
# +1.5 °C of correction is 2.7 °F, not 34.7 °F, and |-5 °C| is no temperature of 5 °C
DIFFERENCE_WORDS = frozenset({"correction", "offset", "delta", "difference", "deviation",
                              "hysteresis", "deadband", "magnitude", "adjustment",
                              "compensation"})


def first_clause(text: str) -> str:
    """A description up to its first aside (`` (`` or ``; ``), without a trailing
    ``.:,``, capitalised: ``"kWh (+) total"`` -> ``"KWh"``; "" for none."""
    out = _ASIDE.split(text, maxsplit=1)[0].strip().rstrip(".:,")
    return out[:1].upper() + out[1:]


def is_difference(name: str, title: str) -> bool:
    """Whether a field of this name and title is a difference of its unit (a word of
    either is one of ``DIFFERENCE_WORDS``): ``Field.difference``, and the same rule for
    a field known only by its name and label (a fleet viewer's ``bridge/info``)."""
    words = set(name.split("_")) | set(re.findall(r"[a-z]+", title.lower()))
    return not DIFFERENCE_WORDS.isdisjoint(words)


def squashed(text: str) -> str:
    """Text compared as a label or unit is: without spaces, case folded."""
    return "".join(text.split()).casefold()


class Addressing(str, enum.Enum):
    """How the manual writes register addresses, and so how to get the wire address.

    ``pdu``: the address as sent in the request (0-based, e.g. 0x0006).
    ``direct``: a Modicon-looking reference sent literally (30006 goes out as 0x7536).
    ``modicon``: a 3xxxx/4xxxx reference; the wire address is the reference - 30001/40001
    (or, past 9999, a 6-digit 3xxxxx/4xxxxx one: the reference - 300001/400001).
    ``one_based``: a register number N; the wire address is N - 1.
    """

    PDU = "pdu"
    DIRECT = "direct"
    MODICON = "modicon"
    ONE_BASED = "one_based"

    def to_wire(self, table: Table, written: int) -> int:
        if self is Addressing.MODICON:
            base = table.modicon_base
            return int(written - (base * 10 if written > base + 9999 else base) - 1)
        if self is Addressing.ONE_BASED:
            return written - 1
        return written

    def to_written(self, table: Table, wire: int) -> int:
        if self is Addressing.MODICON:
            base = table.modicon_base
            return int(wire + (base if wire < 9999 else base * 10) + 1)
        if self is Addressing.ONE_BASED:
            return wire + 1
        return wire

    def show(self, table: Table, wire: int) -> str:
        """The address as the manual writes it."""
        written = self.to_written(table, wire)
        return f"0x{written:04X}" if self is Addressing.PDU else str(written)


def is_modicon_reference(table: Table, reference: int) -> bool:
    """A 5-digit (30001..39999) or 6-digit (300001..365536) reference into ``table``."""
    base = table.modicon_base
    six = base * 10
    return base < reference <= base + 9999 or six < reference <= six + 65536


class Severity(str, enum.Enum):
    OK = "ok"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"

    @property
    def rank(self) -> int:
        return ["ok", "info", "warning", "error"].index(self.value)


class Poll(str, enum.Enum):
    """When a field is read: ``default`` in every poll and default read; ``on_request``
    only when named; ``never``: reading it has side effects, so no request may touch it."""

    DEFAULT = "default"
    ON_REQUEST = "on_request"
    NEVER = "never"


@frozen
class Choice:
    """One enum code or flag bit: its name, severity and meaning."""

    name: str
    severity: Severity = Severity.OK
    description: str = ""


@frozen
class Field:
    name: str
    table: Table
    address: int  # as sent on the wire
    layout: Layout
    written: str = ""  # the address as the manual writes it
    unit: str = ""
    description: str = ""
    access: str = "R"  # R, RW or W
    enum: Mapping[int, Choice] = dataclasses.field(default_factory=dict)
    other: Choice | None = None  # enum: what every undocumented code means ("other:" in YAML)
    flags: Mapping[int, Choice] = dataclasses.field(default_factory=dict)  # bit mask -> flag
    minimum: float | None = None  # the documented range of the value
    maximum: float | None = None
    values: tuple[float, ...] = ()  # the only values it takes (e.g. supported baud rates)
    poll: Poll = Poll.DEFAULT
    alone: bool = False  # must be read in a request of its own
    since: int = 0  # first variant (e.g. IRNET data structure) that has it
    source: str = "manual"  # "manual", or "public" for facts from outside the seed manual
    # stored values (before scale) that mean "no reading": "not available", "sensor error"
    sentinels: Mapping[int | float, Choice] = dataclasses.field(default_factory=dict)
    precision: int | None = None  # decimal places the value is rounded to
    interval: float | None = None  # seconds between reads when polled (None: the device's;
    #                                inf: read once at start, ``interval: once``)
    # a total that only grows (energy, operating hours): outputs may mark it
    # ``total_increasing`` (Home Assistant) or as a counter (Prometheus)
    counter: bool = False
    typical: float | str | None = None  # an everyday value: where the simulator starts
    # fields of the same device the value is multiplied by (a CT or VT ratio): the
    # registers hold the meter's terminal-side value (``model.scaling``)
    scale_by: tuple[str, ...] = ()
    # a documented encoding the stored number is unfolded by (``decode:``, model.transforms)
    transform: Transform | None = None
    label: str = ""  # the profile's ``label:`` ("" when it gives none: see ``title``)
    line: int = 0

    @property
    def title(self) -> str:
        """The field's short name for people (Home Assistant's entity name, the
        dashboard's column): its ``label``, else its description up to the first aside,
        else its name in words (``import_active_energy`` -> ``"Import active energy"``)."""
        if self.label:
            return self.label
        text = first_clause(self.description) or self.name.replace("_", " ")
        return text[:1].upper() + text[1:]

    @property
    def difference(self) -> bool:
        """Whether the value is a difference of its unit (a correction, an offset, a
        delta, a hysteresis, a magnitude without its sign), by a word of its name or
        title (``DIFFERENCE_WORDS``): shown and announced in its unit as it is, never
        converted as an absolute value (kelvin to °C, HA's °C to °F) would be."""
        return is_difference(self.name, self.title)

    @property
    def words(self) -> int:
        return self.layout.words

    @property
    def end(self) -> int:
        """One past the last wire register."""
        return self.address + self.layout.words

    @property
    def writable(self) -> bool:
        return "W" in self.access

    def can_share(self, other: Field) -> bool:
        """Whether this field may occupy a register ``other`` also occupies: only one-register
        fields whose bits do not overlap (two u8 halves, bit fields of a status word)."""
        return self.words == other.words == 1 and not self.layout.mask & other.layout.mask

    @property
    def range(self) -> bool:
        return self.minimum is not None and self.maximum is not None


@frozen
class Serial:
    baudrate: int = 9600
    parity: str = "N"
    bytesize: int = 8
    stopbits: int = 1
    baudrates: tuple[int, ...] = ()  # every rate the device can be set to
    deassert_dtr: bool = False  # open the port with DTR and RTS deasserted (DTR resets some boards)


IDLE_GAP_MAX = 10.0  # seconds: the longest ``idle_gap`` a device may be given


def idle_gap_error(gap: float) -> str | None:
    """Why ``gap`` (seconds) cannot be an idle gap (profile, site file, --idle-gap)."""
    return None if 0 <= gap <= IDLE_GAP_MAX else f"{gap:g} s is outside 0..{IDLE_GAP_MAX:g} s"


@frozen
class Limits:
    max_registers: int = MAX_REGISTERS  # per read request
    max_gap: int = 0  # unread registers a block may bridge (0: blocks only over adjacent fields)
    functions: frozenset[int] = frozenset({3, 4, 6, 16})
    timeout: float = 0.5  # response timeout hint, seconds
    retries: int = 1
    turnaround: float = 0.005  # typical time from request end to reply start, seconds
    silent_on_error: bool = False  # malformed/unsupported requests get no reply at all
    lost_after_powerup: int = 0  # requests a freshly powered device may drop
    idle_gap: float = 0.0  # silence on the line the device needs before a request, seconds


@frozen
class Addresses:
    lo: int = 1
    hi: int = 247
    default: int = 1
    reserved: Mapping[int, str] = dataclasses.field(default_factory=dict)  # address -> why
    any: int | None = None  # an address every such device answers (CO2Meter 0xFE)

    def check(self, address: int) -> str | None:
        """Why ``address`` cannot be assigned to this device, or None when it can."""
        if address == 0:
            return "0 is the broadcast address"
        if address == self.any:
            return f"{address} (0x{address:02X}) is the 'any device' address of this device"
        if address in self.reserved:
            return f"{address} (0x{address:02X}) is reserved: {self.reserved[address]}"
        if not self.lo <= address <= self.hi:
            return f"{address} is outside this device's range {self.lo}..{self.hi}"
        return None


@frozen
class Check:
    """One identify check: read ``field`` and test it."""

    field: str
    range: tuple[float, float] | None = None
    equals_address: bool = False
    equals: tuple[str | int | float, ...] = ()  # any of these values
    exception: int | None = None  # this exception code also counts as a match


@frozen
class AddressChange:
    """How the device's own address is changed, or why it cannot be from here."""

    field: str | None = None
    function: int = 6
    reply: str = "echo"  # echo | none | malformed | any: what the device answers to the write
    unsupported: str = ""  # what the manual says instead, when field is None


@frozen
class Variant:
    """A register that tells which generation of the map the device has."""

    field: str
    name: str
    # exception code on reading the field -> the variant it means
    on_exception: Mapping[int, int] = dataclasses.field(default_factory=dict)


class Verification(str, enum.Enum):
    """How far a profile's register map is verified (``provenance.level``)."""

    VENDOR = "vendor document"  # written from, and checked against, the vendor's own document
    TWO = "two independent implementations"  # no vendor document: two public sources agree
    UNVERIFIED = "unverified"  # nobody could check it: values may be wrong


@frozen
class Document:
    """One document a profile was written from."""

    title: str
    where: str  # a URL, or a repository and path
    version: str = ""

    def __str__(self) -> str:
        return f"{self.title}" + (f" ({self.version})" if self.version else "") \
            + f" <{self.where}>"


@frozen
class Provenance:
    """Where a profile's facts come from, and how far they are verified."""

    level: Verification = Verification.UNVERIFIED
    sources: tuple[Document, ...] = ()
    notes: str = ""
    given: bool = False  # False: the profile has no provenance block at all

    @property
    def verified(self) -> bool:
        return self.level is not Verification.UNVERIFIED

    @property
    def label(self) -> str:
        return self.level.value if self.given else "unverified (no provenance)"


def _not_said() -> AddressChange:
    return AddressChange(unsupported="the profile does not say")


@frozen
class Profile:
    id: str
    vendor: str
    model: str
    manual: str
    addressing: Addressing
    fields: tuple[Field, ...]
    # the sections a file may leave out: made when a profile is, not at import (a cached
    # profile is unpickled whole, and then these classes are never called)
    serial: Serial = dataclasses.field(default_factory=Serial)
    limits: Limits = dataclasses.field(default_factory=Limits)
    addresses: Addresses = dataclasses.field(default_factory=Addresses)
    byte_order: ByteOrder = ByteOrder.ABCD
    identify: tuple[Check, ...] = ()
    set_address: AddressChange = dataclasses.field(default_factory=_not_said)
    variant: Variant | None = None
    notes: str = ""
    kind: str = ""  # what sort of device: energy meter, gas sensor, solar charger, ...
    extends: str = ""  # the id of the profile this one was built on
    provenance: Provenance = dataclasses.field(default_factory=Provenance)
    path: str = ""
    # what the device says of itself: read device identification's objects (FC 43/14:
    # object id -> text) and report server id's server id bytes (FC 17), as documented
    identification: tuple[tuple[int, str], ...] = ()
    server_id: bytes = b""
    # what the loader found doubtful but not wrong (``file:line: path: warning``): two
    # fields with one title, a title that is only a unit or too long, in a profile that
    # gives those fields no ``label:``; ``rtupoll profiles check`` prints them
    warnings: tuple[str, ...] = ()

    def line_setting(self, field: Field) -> str:
        """What writing ``field`` changes about how the device is reached: "address"
        (the profile's ``set_address.field``, or a field named for an address), "baud"
        (a field in baud, or named for the line speed) or "". A write to either can cut
        the device off the bus: the gateway and MQTT refuse them unless allowed."""
        name = field.name.lower()
        if field.name == self.set_address.field or "address" in name:
            return "address"
        if field.unit.lower() == "baud" or any(w in name for w in _LINE_SPEED_WORDS):
            return "baud"
        return ""

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        from rtupoll.model.names import close_names

        hint = close_names(name, self.names(), n=3)
        raise UsageError(f"{self.id} has no field {name!r}"
                         + (f" (did you mean {' or '.join(map(repr, hint))}?)" if hint else "")
                         + f"; 'rtupoll profiles show {self.id}' lists them")

    def names(self) -> list[str]:
        return [f.name for f in self.fields]

    def default_fields(self) -> tuple[Field, ...]:
        return tuple(f for f in self.fields if f.poll is Poll.DEFAULT)

    def forbidden(self) -> tuple[Field, ...]:
        return tuple(f for f in self.fields if f.poll is Poll.NEVER)

    def written(self, f: Field) -> str:
        return self.addressing.show(f.table, f.address)
