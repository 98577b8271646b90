"""Finding devices on a bus: the sweep plan, its timing, and identification by profile.

A sweep is mostly silence: of 247 addresses a handful answer, so the time of a scan
is the number of dead addresses times the time it takes to be sure nobody answers.
That time is derived from the wire, not guessed: the request, the longest reply the
probe can get, the inter-frame silence, and a turnaround margin for the device and
the adapter. Everything that answers - a reply, an exception, even a garbled frame -
means "something is there"; only then is it worth more requests to learn what.

Identification runs each profile's ``identify`` checks (a register in a range, the
address register equal to the address, an expected exception), never "any reply".
The order is chosen so a scan stays fast and honest:

- one presence probe per address, chosen so that every ``silent_on_error`` profile
  answers it (the others answer anything, with an exception at worst), so a dead
  address costs exactly one timeout;
- every answer is cached per address, so a check already answered by an earlier
  request costs nothing, and a profile that contradicts an answer is never probed;
- an address whose answer arrives after its probe timed out (the line counts it late,
  ``BusLike.unit_counts``) is asked again with a longer timeout
  (``jobs.timeouts.late_margin``: twice the late reply's time) before it is called
  empty, so a slow device is found without making every empty address wait for it;
- a present unit that leaves a read unanswered is asked it again, waiting longer; a
  read still unanswered is explained only by a ``silent_on_error`` profile, so a busy
  moment makes a device "unknown" (present, not identified), never another model;
- the most specific profiles (most checks) are tried first, so a one-check profile
  (CO2Meter: one register in 0..10000) only claims a device nothing else explains.

Pure apart from the bus (any ``rtupoll.io.interface.BusLike``), so it is testable offline.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass, field

from rtupoll.errors import DeviceException, DeviceTimeout, FrameError, UsageError
from rtupoll.io.interface import BusLike
from rtupoll.jobs.timeouts import late_margin
from rtupoll.model.identify import check_passes
from rtupoll.model.profile import Profile
from rtupoll.rtu import ExceptionCode, Framing, Table, exception_name, read_frame_sizes

LATENCY = 0.02  # USB-serial adapters deliver a reply up to a latency-timer tick late
LATE_WAIT = 4  # after the last address, late answers are awaited this many reply waits


Read = tuple[Table, int, int]  # table, wire address, count
Outcome = tuple[int, ...] | DeviceException | DeviceTimeout | FrameError


@dataclass(frozen=True)
class Setting:
    """One serial setting to sweep."""

    baudrate: int
    parity: str = "N"

    def __str__(self) -> str:
        return f"{self.baudrate} 8{self.parity}1"

    @property
    def framing(self) -> Framing:
        return Framing(self.baudrate, 8, self.parity, 1)


@dataclass
class Found:
    """Something that answered at one address and setting, and what it turned out to be."""

    address: int
    setting: Setting
    profile: Profile | None = None
    evidence: list[str] = field(default_factory=list)  # checks passed, for the identified
    answers: list[str] = field(default_factory=list)  # what it answered to, for the unknown
    garbled: bool = False  # only unusable frames came back: wrong speed, or a collision

    @property
    def status(self) -> str:
        return "identified" if self.profile else ("garbled" if self.garbled else "unknown")


def parse_addresses(text: str) -> tuple[int, ...]:
    """``1-20,100`` -> addresses, in the order given, without repeats."""
    out: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        lo, sep, hi = part.partition("-")
        try:
            a, b = int(lo, 0), int(hi, 0) if sep else int(lo, 0)
        except ValueError:
            raise UsageError(f"{part!r} is not an address or range (e.g. 1-20,100)") from None
        if not 0 <= a <= b <= 255:
            raise UsageError(f"{part!r}: addresses are 0..255, low to high")
        out += [x for x in range(a, b + 1) if x not in out]
    return tuple(out)


def parse_list(text: str, what: str, convert: Callable[[str], object]) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    for t in items:
        try:
            convert(t)
        except ValueError:
            raise UsageError(f"{t!r} is not a {what}") from None
    return items


def skipped(addresses: Iterable[int], profiles: Iterable[Profile]) -> dict[int, str]:
    """Addresses a sweep must not send to unless asked, and why.

    0 is broadcast (nobody answers, every device acts); an 'any device' address is
    answered by every such device at once; a reserved one may trigger another protocol.
    """
    why: dict[int, str] = {}
    wanted = set(addresses)
    if 0 in wanted:
        why[0] = "broadcast: every device acts on it and none answers"
    profiles = list(profiles)
    for p in profiles:  # an 'any device' address first: devices answer there
        if p.addresses.any in wanted and p.addresses.any is not None:
            why.setdefault(p.addresses.any, f"every {p.id} answers it ('any device' address)")
    for p in profiles:
        for a, reason in p.addresses.reserved.items():
            if a in wanted:
                why.setdefault(a, f"reserved by {p.id}: {reason}")
    return why


def default_baudrates(profiles: Iterable[Profile]) -> list[int]:
    """Every rate a library device runs at, the most common default first."""
    counts: dict[int, tuple[int, int]] = {}
    for p in profiles:
        for rate in p.serial.baudrates or (p.serial.baudrate,):
            d, n = counts.get(rate, (0, 0))
            counts[rate] = (d + (rate == p.serial.baudrate), n + 1)
    return sorted(counts, key=lambda r: (-counts[r][0], -counts[r][1], r))


def presence_probes(profiles: Sequence[Profile]) -> list[Read]:
    """The fewest reads such that every library device answers at least one.

    Devices that are silent on errors answer only functions they support; everyone
    else answers anything (an exception at worst). So each silent profile needs a
    probe with a function it supports; its first identify check's read is used, so
    the probe's answer is already evidence.
    """
    probes: list[Read] = []
    silent = [p for p in profiles if p.limits.silent_on_error and p.identify]
    for p in sorted(silent, key=lambda p: p.id):
        if any(t.read_function in p.limits.functions for t, _, _ in probes):
            continue
        f = p.field(p.identify[0].field)
        probes.append((f.table, f.address, f.words))
    if not probes:
        first = sorted((p for p in profiles if p.identify), key=lambda p: -len(p.identify))
        if first:
            f = first[0].field(first[0].identify[0].field)
            probes.append((f.table, f.address, f.words))
        else:
            probes.append((Table.HOLDING, 0, 1))
    return probes


def probe_timeout(framing: Framing, count: int, margin: float) -> float:
    """How long to wait for the answer to one read of ``count`` registers.

    The request and the longest normal reply on the wire, the inter-frame silence the
    device waits before answering, and the turnaround margin.
    """
    request, reply = read_frame_sizes(count)
    return framing.wire_time(request + reply) + reply_wait(framing, margin)


PRESENT = 4  # times the probe's wait, the second ask of a read a present unit did not answer


def reply_wait(framing: Framing, margin: float) -> float:
    """The part of ``probe_timeout`` that is not wire time: what ``Bus.read`` is given
    as its timeout, since the bus adds the frames' wire time itself."""
    return framing.silence + margin


def default_margin(profiles: Iterable[Profile]) -> float:
    """The slowest typical turnaround in the library, plus adapter latency."""
    return max((p.limits.turnaround for p in profiles), default=0.01) + LATENCY


def sweep_time(settings: Sequence[Setting], addresses: int, probes: Sequence[Read],
               margin: float) -> float:
    """The time a sweep takes when nothing answers: the floor for these timeouts.

    The silence before the next request has long passed when a timeout expires, so an
    empty address costs its probes' timeouts and nothing else.
    """
    return sum(addresses * sum(probe_timeout(s.framing, n, margin) for _, _, n in probes)
               for s in settings)


def describe(read: Read, outcome: Outcome) -> str:
    """What one read got, for an unknown device's list of answers."""
    table, address, count = read
    what = f"{table.value} 0x{address:04X}" + (f"+{count}" if count > 1 else "")
    if isinstance(outcome, DeviceException):
        name = "" if outcome.code == ExceptionCode.ILLEGAL_ADDRESS \
            else f" {exception_name(outcome.code).lower()}"
        return f"{what}: exception {outcome.code:02d}{name}"
    if isinstance(outcome, DeviceTimeout):
        return f"{what}: no answer"
    if isinstance(outcome, FrameError):
        return f"{what}: garbled reply"
    return f"{what}: " + " ".join(f"{w:04X}" for w in outcome)


class Identifier:
    """Asks one address the questions that tell which profile it is, caching every answer."""

    def __init__(self, bus: BusLike, profiles: Sequence[Profile], setting: Setting,
                 margin: float) -> None:
        self.bus, self.setting, self.margin = bus, setting, margin
        self.profiles = [p for p in profiles if p.identify]

    async def ask(self, cache: dict[Read, Outcome], unit: int, read: Read, *,
                  present: bool = False) -> Outcome:
        """One read's outcome, asked once. ``present``: the unit answered already, so a
        read it does not answer is asked once more, waiting longer (a busy device, or a
        busy machine's simulator, is no evidence against a profile), where an empty
        address costs one timeout."""
        if read not in cache:
            table, address, count = read
            timeout = reply_wait(self.setting.framing, self.margin)
            try:
                cache[read] = (await self.bus.read(unit, table, address, count,
                                                   timeout=timeout, retries=0)).values
            except DeviceTimeout as exc:
                cache[read] = exc
                if present:
                    await self._again(cache, unit, read, PRESENT * timeout)
            except (DeviceException, FrameError) as exc:
                cache[read] = exc
        return cache[read]

    async def _again(self, cache: dict[Read, Outcome], unit: int, read: Read,
                     timeout: float) -> None:
        table, address, count = read
        try:
            cache[read] = (await self.bus.read(unit, table, address, count,
                                               timeout=timeout, retries=0)).values
        except (DeviceException, DeviceTimeout, FrameError) as exc:
            cache[read] = exc

    def order(self, cache: dict[Read, Outcome], unit: int) -> list[Profile]:
        """Candidates, most specific first; those an earlier answer contradicts are dropped."""
        ranked = []
        for p in self.profiles:
            passed, failed = 0, False
            for c in p.identify:
                f = p.field(c.field)
                got = cache.get((f.table, f.address, f.words))
                if got is None:
                    continue
                if check_passes(c, p, unit, got):
                    passed += 1
                else:
                    failed = True
                    break
            if not failed:
                at_speed = self.setting.baudrate in (p.serial.baudrates or (p.serial.baudrate,))
                ranked.append((not at_speed, -len(p.identify), -passed, p.id, p))
        return [r[-1] for r in sorted(ranked, key=lambda r: r[:4])]

    async def identify(self, unit: int, cache: dict[Read, Outcome]) -> tuple[Profile | None,
                                                                               list[str]]:
        for p in self.order(cache, unit):
            evidence = []
            for c in p.identify:
                f = p.field(c.field)
                got = await self.ask(cache, unit, (f.table, f.address, f.words),
                                     present=True)
                why = check_passes(c, p, unit, got)
                if why is None:
                    break
                evidence.append(why)
            else:
                quirk = await self.quirks(p, unit, cache)
                if quirk is not None:
                    return p, [*evidence, quirk] if quirk else evidence
        return None, []

    async def quirks(self, p: Profile, unit: int, cache: dict[Read, Outcome]) -> str | None:
        """Evidence beyond the identify checks ("" for none), or None when the device
        contradicts ``p``.

        A device that answers a function the profile does not support is not that
        device. A read the unit left unanswered, asked twice, is explained only by a
        ``silent_on_error`` profile: any other answers everything (an exception at
        worst), so the silence is a busy moment, and naming it from the other answers
        could name the wrong model (a SDM630 whose frequency read was lost answers all
        an SDM72D asks): it stays present, not identified. A ``silent_on_error`` profile
        (typically with a single loose check, e.g. one register in 0..10000) is asked one
        unsupported read, which it must ignore: a device that answers it is something else.
        """
        for (table, _, _), got in cache.items():
            if isinstance(got, tuple) and table.read_function not in p.limits.functions:
                return None
            if isinstance(got, DeviceTimeout) and not p.limits.silent_on_error:
                return None  # it answers every read: this silence is a busy moment unexplained
        if not p.limits.silent_on_error:
            return ""
        odd = next((t for t in (Table.COIL, Table.DISCRETE, Table.HOLDING, Table.INPUT)
                    if t.read_function not in p.limits.functions), None)
        if odd is None:
            return ""
        got = await self.ask(cache, unit, (odd, 0, 1))
        if not isinstance(got, DeviceTimeout):
            return None
        return f"ignores function {odd.read_function:02d}, as {p.id} does"


async def probe_address(bus: BusLike, identifier: Identifier, probes: Sequence[Read],
                        unit: int) -> Found | None:
    """Is anything at ``unit``? If so, what is it? One timeout per probe when nothing is."""
    cache: dict[Read, Outcome] = {}
    for read in probes:
        await identifier.ask(cache, unit, read)
    if all(isinstance(o, DeviceTimeout) for o in cache.values()):
        return None
    for read in [r for r in probes if isinstance(cache[r], DeviceTimeout)]:
        del cache[read]  # present: a probe it did not answer is asked again, as any read
        await identifier.ask(cache, unit, read, present=True)
    found = Found(unit, identifier.setting)
    if all(isinstance(o, (DeviceTimeout, FrameError)) for o in cache.values()):
        found.garbled = True
        found.answers = [describe(r, o) for r, o in cache.items()]
        return found
    found.profile, found.evidence = await identifier.identify(unit, cache)
    if found.profile is None:
        found.answers = [describe(r, o) for r, o in cache.items()
                         if not isinstance(o, DeviceTimeout)]
    return found


async def sweep(open_bus: Callable[[Setting], AbstractAsyncContextManager[BusLike]],
                settings: Sequence[Setting], addresses: Sequence[int],
                profiles: Sequence[Profile], *, margin: float, probes: Sequence[Read],
                found: list[Found], progress: Callable[[Setting, int], None] = lambda s, a: None,
                first: bool = False) -> None:
    """Probe every address at every setting, appending to ``found`` as it goes.

    ``found`` belongs to the caller, so an interrupted sweep still has its results.
    ``first`` stops after the first setting at which anything was identified.
    """
    for setting in settings:
        async with open_bus(setting) as bus:
            identifier = Identifier(bus, profiles, setting, margin)
            empty: list[int] = []  # so far: an answer that comes late gets a second chance
            for unit in addresses:
                result = await probe_address(bus, identifier, probes, unit)
                if result is not None:
                    found.append(result)
                else:
                    empty.append(unit)
                found += await _late_ones(bus, profiles, setting, margin, probes, empty)
                progress(setting, unit)
            # the last addresses' late answers may still be on their way
            if empty:
                await asyncio.sleep(LATE_WAIT * reply_wait(setting.framing, margin))
                found += await _late_ones(bus, profiles, setting, margin, probes, empty)
        if first and any(f.setting == setting and f.profile for f in found):
            return


async def _late_ones(bus: BusLike, profiles: Sequence[Profile], setting: Setting,
                     margin: float, probes: Sequence[Read], empty: list[int]) -> list[Found]:
    """Addresses called empty whose answer has come in late since: asked again with a
    longer timeout (``jobs.timeouts.late_margin``), before they are called empty."""
    out: list[Found] = []
    for unit in [u for u in empty if bus.unit_counts(u).late]:
        empty.remove(unit)
        took = bus.unit_counts(unit).late_reply_time
        longer = Identifier(bus, profiles, setting, late_margin(margin, took))
        result = await probe_address(bus, longer, probes, unit)
        if result is not None:
            result.evidence.append(f"answered late at first (in {took * 1000:.0f} ms)"
                                   if took is not None else "answered late at first")
            out.append(result)
    return out


def merged(found: Sequence[Found]) -> list[Found]:
    """Drop garbled answers at an address that answered properly at another setting.

    At the wrong speed a device often answers noise; that is not a second device.
    """
    good = {f.address for f in found if not f.garbled}
    return sorted((f for f in found if not f.garbled or f.address not in good),
                  key=lambda f: (f.address, f.setting.baudrate, f.setting.parity))


def every_speed(found: Sequence[Found], settings: Sequence[Setting]) -> bool:
    """Whether every device answered at every baud rate scanned (more than one).

    No real line does that: all devices on a pair share one speed, and a device at the
    wrong one hears noise. A simulator without wire timing, or a gateway that fixes the
    serial speed itself, does; ``scan`` then says so and lists each device once.
    """
    rates = {s.baudrate for s in settings}
    seen: dict[int, set[int]] = {}
    for f in found:
        if not f.garbled:
            seen.setdefault(f.address, set()).add(f.setting.baudrate)
    return len(rates) > 1 and bool(seen) and all(r == rates for r in seen.values())


def once_each(found: Sequence[Found]) -> list[Found]:
    """One answer per address: at its profile's default speed if it answered there."""
    best: dict[int, Found] = {}
    for f in found:
        have = best.get(f.address)
        if have is None or (f.profile is not None and
                            f.setting.baudrate == f.profile.serial.baudrate and
                            (have.profile is None or
                             have.setting.baudrate != have.profile.serial.baudrate)):
            best[f.address] = f
    return [best[a] for a in sorted(best)]
