"""A gateway's identity on a shared broker, and what it tells a fleet viewer about itself.

Several rtupoll gateways may publish to one broker. Each has a stable ``gateway_id``
(``--mqtt-id``, site file ``mqtt.gateway_id``, default: the machine's host name,
lower-cased, every character other than ``[a-z0-9_-]`` as ``_``), which names its
default base topic (``rtupoll/<gateway_id>``) and its Home Assistant ids
(``rtupoll_<gateway_id>_<device>``). ``BASE/bridge/info`` (retained) says who it is
and what its devices and fields are, with each field's label, unit, kind and
precision, an enum's or flag set's names with their severities, and a field's
sentinels' names with theirs: what a fleet viewer (``rtupoll web --mqtt``) needs to show
it as the gateway's own dashboard does.

Pure: no MQTT library, no I/O but the host name.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from rtupoll.model.interpret import (
    field_kind,
    severities,
    shown_precision,
    unlisted_severity,
)
from rtupoll.model.profile import first_clause

if TYPE_CHECKING:
    from rtupoll.config.site import BusConfig, DeviceConfig
    from rtupoll.model.profile import Choice, Field

# the key of rtupoll's own status in a state message: no profile field can take it
# (field names are lower_snake_case identifiers that do not start with "_")
STATUS_KEY = "_rtupoll"
LAST_SEEN = "last_seen"
# under STATUS_KEY, while a field's value is a sentinel: field -> the sentinel's name
SENTINELS = "sentinels"
RESERVED = (STATUS_KEY, LAST_SEEN)  # keys of a state message that are not fields


def choice_label(choice: Choice) -> str:
    """A flag's or enum value's name for people: its description, else its name."""
    return first_clause(choice.description) or choice.name


def field_info(field: Field) -> dict[str, Any]:
    """A field as ``bridge/info`` tells a fleet viewer of it: its title, the device's
    unit, and the kind and precision every screen goes by (``model.interpret``); for an
    enum or flags field, ``severities``: each name it can hold with its severity, and
    ``unlisted``: the severity of a name not there (``unknown (9)``, ``bit 3``), from
    which a reading's severity is ``model.interpret.reading_severity``'s; for a field
    with sentinels, ``sentinels``: each one's name with its severity (a state message
    names the one a field holds, ``SENTINELS``)."""
    kind = field_kind(field)
    out: dict[str, Any] = {"label": field.title, "unit": field.unit, "kind": kind,
                           "precision": shown_precision(field)}
    if kind in ("enum", "flags"):
        out["severities"] = {n: s.value for n, s in severities(field).items()}
        out["unlisted"] = unlisted_severity(field).value
    if field.sentinels:
        out["sentinels"] = {c.name: c.severity.value for c in field.sentinels.values()}
    return out


def bridge_info(gateway_id: str, base: str, devices: Iterable[tuple[BusConfig, DeviceConfig]],
                topics: dict[str, str], version: str) -> dict[str, Any]:
    """The retained ``BASE/bridge/info`` payload. Devices are keyed by their topic level
    (``BASE/<key>`` is their state), with the site's name under ``name``."""
    out: dict[str, Any] = {}
    for bus, dev in devices:
        t = topics.get(dev.name, dev.name)
        out[t] = {"name": dev.name, "profile": dev.profile.id, "address": dev.address,
                  "bus": bus.name,
                  "fields": {f.name: field_info(f) for f in dev.fields}}
    return {"gateway": gateway_id, "version": version, "base": base, "devices": out}


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("rtupoll")
    except PackageNotFoundError:
        return "unknown"
