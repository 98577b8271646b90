"""Home Assistant MQTT discovery, generated from the profiles.

One retained message per Modbus device in HA's device-based form
(``PREFIX/device/OBJECT_ID/config`` with ``dev``, ``o`` and ``cmps``), one per bus
(the HA device the sensors are ``via_device``), so removing a device is one empty
retained payload. Per polled field:

- a number: a ``sensor`` with its unit, and ``device_class``/``state_class`` where the
  unit implies one (°C, %RH, ppm of CO2, µg/m³ of PM2.5, V, A, W, kWh, ...), none for a
  difference (a correction, an offset), ``power_factor`` for a power factor;
- an enum: an ``enum`` sensor whose options are the profile's names (plus the
  catch-all name and ``unknown`` for codes the manual does not list);
- a flag set: one ``binary_sensor`` per flag (``problem`` when its severity is a
  warning or an error); a bool (coil): one ``binary_sensor``;
- text: a plain ``sensor``;
- with writes on, a writable enum is also a ``select`` and a writable number a
  ``number``, both sending ``{"FIELD": value}`` to ``BASE/DEVICE/set``.

Every entity reads ``BASE/DEVICE`` (``value_json``; a failed read is null, which HA
shows as unknown; every polled field is in every message, ``outputs.mqtt_state``) and
is available only when both ``BASE/bridge/state`` and ``BASE/DEVICE/availability`` say
``online``. Identifiers are ``rtupoll_<gateway_id>_<device>[_<entity>]``: the same on
every run, and distinct between gateways on one broker. Names are the profile's labels
(``Field.title``); an enum code the manual does not list is ``unknown`` in the
enum sensor and no option in a select; a number box spans what the profile allows.
Each device also has two diagnostic entities from ``_rtupoll`` and ``last_seen``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from rtupoll.model.codec import DataType, value_range
from rtupoll.model.interpret import shown_precision
from rtupoll.model.profile import Field, Severity
from rtupoll.outputs.fleet import (
    LAST_SEEN,
    STATUS_KEY,
    choice_label,
    version,
)

if TYPE_CHECKING:
    from rtupoll.config.site import BusConfig, DeviceConfig

ORIGIN_NAME = "rtupoll"
STATUSES = ("ok", "partial", "failed")  # _rtupoll.status in a state message
MIN_STEP = 0.001  # the smallest step Home Assistant accepts for a number
# profile unit -> (Home Assistant unit, device class); ppm and µg/m³ depend on the field
_UNITS: dict[str, tuple[str, str | None]] = {
    "°C": ("°C", "temperature"), "°F": ("°F", "temperature"), "K": ("K", "temperature"),
    "%RH": ("%", "humidity"), "%rh": ("%", "humidity"),
    "V": ("V", "voltage"), "mV": ("mV", "voltage"), "kV": ("kV", "voltage"),
    "A": ("A", "current"), "mA": ("mA", "current"),
    "W": ("W", "power"), "kW": ("kW", "power"), "MW": ("MW", "power"),
    "VA": ("VA", "apparent_power"), "kVA": ("kVA", "apparent_power"),
    "var": ("var", "reactive_power"), "kvar": ("kvar", "reactive_power"),
    "Wh": ("Wh", "energy"), "kWh": ("kWh", "energy"), "MWh": ("MWh", "energy"),
    "Hz": ("Hz", "frequency"),
    "Pa": ("Pa", "pressure"), "hPa": ("hPa", "pressure"), "kPa": ("kPa", "pressure"),
    "bar": ("bar", "pressure"), "mbar": ("mbar", "pressure"), "psi": ("psi", "pressure"),
    "mm": ("mm", "distance"), "cm": ("cm", "distance"), "m": ("m", "distance"),
    "km": ("km", "distance"),
    "lx": ("lx", "illuminance"),
    "s": ("s", "duration"), "min": ("min", "duration"), "h": ("h", "duration"),
    "d": ("d", "duration"),
    "m³": ("m³", "volume"), "L": ("L", "volume"), "m³/h": ("m³/h", "volume_flow_rate"),
    "L/min": ("L/min", "volume_flow_rate"), "dB": ("dB", "sound_pressure"),
    "dBm": ("dBm", "signal_strength"), "W/m²": ("W/m²", "irradiance"),
    "µS/cm": ("µS/cm", "conductivity"), "mS/cm": ("mS/cm", "conductivity"),
    "S/cm": ("S/cm", "conductivity"),
    "m/s": ("m/s", "speed"), "km/h": ("km/h", "speed"),
}
_ENERGY = {"energy"}
_UNSAFE = re.compile(r"[^A-Za-z0-9_-]")


def safe_id(text: str) -> str:
    """Letters, digits, ``_`` and ``-`` only: what HA accepts in object ids."""
    return _UNSAFE.sub("_", text)


def object_id(gateway_id: str, name: str) -> str:
    """``rtupoll_<gateway_id>_<device>``: unique on a broker shared by several gateways."""
    return safe_id(f"rtupoll_{gateway_id}_{name}")


def bus_object_id(gateway_id: str, bus: str) -> str:
    return safe_id(f"rtupoll_{gateway_id}_bus_{bus}")


def origin() -> dict[str, str]:
    """Who published the discovery (HA shows it in the device's MQTT info). No ``url``:
    rtupoll has no public home page to point to yet."""
    return {"name": ORIGIN_NAME, "sw": version()}


def config_topic(prefix: str, oid: str) -> str:
    return f"{prefix}/device/{oid}/config"


def classify(field: Field) -> tuple[str, str | None, str | None]:
    """(HA unit, device class, state class) of a numeric field. A device class only where
    Home Assistant's handling of it is right for the field: a difference (a correction,
    an offset: ``Field.difference``) has none, since HA would convert +1.5 °C as a
    temperature, 34.7 °F; a power factor, unitless or in %, is ``power_factor``."""
    unit, cls = _UNITS.get(field.unit, (field.unit, None))
    name = field.name.lower()
    if field.difference:
        cls = None
    elif field.unit in ("", "%") and re.search(r"power_?factor|cos_?phi", name):
        cls = "power_factor"
    elif cls == "speed" and "wind" in name:
        cls = "wind_speed"
    elif field.unit == "ppm":
        cls = "carbon_dioxide" if "co2" in name else (
            "volatile_organic_compounds_parts" if "voc" in name else None)
    elif field.unit in ("µg/m³", "ug/m3", "μg/m³"):
        unit = "µg/m³"
        cls = ("pm25" if re.search(r"pm_?2[._]?5", name) else "pm10" if "pm10" in name
               else "pm1" if re.search(r"pm_?1(?!\d)", name)
               else "volatile_organic_compounds" if "voc" in name else None)
    if cls == "volume" and not field.counter:
        cls = "volume_storage"  # HA's volume is a total (a meter); what a tank holds is this
    if cls in _ENERGY:
        return unit, cls, "total_increasing" if field.counter else "total"
    return unit, cls, "total_increasing" if field.counter else "measurement"


def _value(field: Field) -> str:
    return f"value_json[{field.name!r}]"


def _options(names: list[str]) -> str:
    """A list of names as a Jinja literal (JSON's list syntax is Jinja's)."""
    return json.dumps(names, ensure_ascii=False)


def number_bounds(field: Field) -> tuple[float, float, float]:
    """(min, max, step) of a writable number, so that Home Assistant's box admits every
    value the profile allows: its ``values:``, else its ``range``, else what the register
    type holds at the field's scale; the step is the scale's (or the precision's)."""
    layout = field.layout
    lo, hi = value_range(layout)
    if field.values:
        lo, hi = min(field.values), max(field.values)
    if field.minimum is not None:
        lo = field.minimum
    if field.maximum is not None:
        hi = field.maximum
    if layout.type.is_float:
        step = 10.0 ** -field.precision if field.precision is not None else MIN_STEP
    else:
        step = abs(layout.scale) or 1.0
    step = max(MIN_STEP, round(step, 9))
    return lo, max(hi, lo + step), step  # HA wants max > min, even for one allowed value


def components(field: Field, *, controls: bool) -> dict[str, dict[str, Any]]:
    """The HA entities of one field, by component id (``field`` or ``field_FLAG``)."""
    uid_base = field.name
    v = _value(field)
    out: dict[str, dict[str, Any]] = {}
    t = field.layout.type
    name = field.title
    if field.enum:
        documented = [c.name for c in field.enum.values()]
        options = list(documented)
        if field.other is not None:
            options.append(field.other.name)
        options.append("unknown")
        options = list(dict.fromkeys(options))
        # "unknown (9)" / "OTHER (9)": the code goes, the name stays; a name the options do
        # not hold (never expected) is "unknown" rather than a value HA would reject
        out[uid_base] = {"p": "sensor", "name": name, "device_class": "enum",
                         "options": options,
                         "value_template": f"{{% set v = {v} %}}{{% if v is none %}}None"
                                           f"{{% else %}}{{% set n = v.split(' (')[0] %}}"
                                           f"{{{{ n if n in {_options(options)} else "
                                           "'unknown' }}{% endif %}"}
        if controls and field.writable:
            # an undocumented code is no option of the select: it shows no option (None)
            out[f"{uid_base}_set"] = {
                "p": "select", "name": f"{name} setting", "options": documented,
                "value_template": f"{{% set v = {v} %}}{{{{ v if v in "
                                  f"{_options(documented)} else None }}}}",
                "command_template": f'{{"{field.name}": "{{{{ value }}}}"}}'}
    elif field.flags:
        for choice in field.flags.values():
            out[f"{uid_base}_{safe_id(choice.name)}"] = {
                "p": "binary_sensor", "name": f"{name}: {choice_label(choice)}",
                **({"device_class": "problem"}
                   if choice.severity in (Severity.WARNING, Severity.ERROR) else {}),
                "value_template": f"{{% if {v} is none %}}None{{% elif {choice.name!r} in "
                                  f"{v} %}}ON{{% else %}}OFF{{% endif %}}"}
    elif t is DataType.BOOL:
        out[uid_base] = {"p": "binary_sensor", "name": name,
                         "value_template": f"{{% if {v} is none %}}None{{% elif {v} %}}ON"
                                           "{% else %}OFF{% endif %}"}
    elif t is DataType.STRING:
        out[uid_base] = {"p": "sensor", "name": name, "value_template": f"{{{{ {v} }}}}"}
    else:
        unit, cls, state_class = classify(field)
        entity: dict[str, Any] = {"p": "sensor", "name": name,
                                  "value_template": f"{{{{ {v} }}}}", "state_class": state_class}
        if unit:
            entity["unit_of_measurement"] = unit
        if cls:
            entity["device_class"] = cls
        places = shown_precision(field)
        if places is not None:
            entity["suggested_display_precision"] = places
        out[uid_base] = entity
        if controls and field.writable:
            lo, hi, step = number_bounds(field)
            control: dict[str, Any] = {
                "p": "number", "name": f"{name} setting", "mode": "box",
                "min": lo, "max": hi, "step": step,
                "value_template": f"{{{{ {v} }}}}",
                "command_template": f'{{"{field.name}": {{{{ value }}}}}}'}
            if unit:
                control["unit_of_measurement"] = unit
            out[f"{uid_base}_set"] = control
    return out


def status_components(state_topic: str) -> dict[str, dict[str, Any]]:
    """rtupoll's own view of the device (``_rtupoll`` and ``last_seen`` in each state
    message), as two diagnostic entities; ids that no field can have (``_``). The status
    changes only when it means something; *Last seen* changes with every message, so it
    is disabled until a user enables it (``enabled_by_default``)."""
    key = STATUS_KEY
    return {
        "_status": {"p": "sensor", "name": "Polling status", "entity_category": "diagnostic",
                    "device_class": "enum", "options": list(STATUSES),
                    "value_template": f"{{{{ value_json[{key!r}].status }}}}",
                    "json_attributes_topic": state_topic,
                    "json_attributes_template": f"{{{{ value_json[{key!r}] | tojson }}}}"},
        # a new state with every message: 86,400 rows a day in HA's recorder at a 1 s
        # interval, on a device whose values never changed; off until a person wants it
        "_last_seen": {"p": "sensor", "name": "Last seen", "entity_category": "diagnostic",
                       "device_class": "timestamp", "enabled_by_default": False,
                       "value_template": f"{{{{ value_json[{LAST_SEEN!r}] }}}}"},
    }


def device_config(dev: DeviceConfig, bus: BusConfig, *, gateway_id: str, base: str,
                  topic: str, controls: Mapping[str, bool], qos: int) -> dict[str, Any]:
    """The discovery payload of one Modbus device; ``topic`` is its topic name,
    ``controls`` which fields get a select/number (writes on, field allowed)."""
    oid = object_id(gateway_id, topic)
    state_topic = f"{base}/{topic}"
    cmps: dict[str, dict[str, Any]] = {}
    for f in dev.fields:
        for cid, entity in components(f, controls=controls.get(f.name, False)).items():
            if entity["p"] in ("select", "number"):
                entity["command_topic"] = f"{base}/{topic}/set"
            cmps[cid] = entity
    cmps.update(status_components(state_topic))
    for cid, entity in cmps.items():
        entity["unique_id"] = f"{oid}_{cid}"
    p = dev.profile
    return {
        "dev": {"ids": [oid], "name": dev.name, "mf": p.vendor, "mdl": p.model,
                "mdl_id": p.id, "via_device": bus_object_id(gateway_id, bus.name)},
        "o": origin(),
        "cmps": cmps,
        "state_topic": state_topic,
        "availability": [{"topic": f"{base}/bridge/state"},
                         {"topic": f"{base}/{topic}/availability"}],
        "availability_mode": "all",
        "qos": qos,
    }


def bus_config(bus: BusConfig, *, gateway_id: str, base: str, qos: int) -> dict[str, Any]:
    """The bus as an HA device: its devices hang off it (``via_device``); its one entity
    says whether the gateway polling it is connected."""
    oid = bus_object_id(gateway_id, bus.name)
    return {
        "dev": {"ids": [oid], "name": f"RS-485 {bus.name} ({gateway_id})", "mf": "rtupoll",
                "mdl": f"RS-485 bus ({bus.serial_text})"},
        "o": origin(),
        "cmps": {"gateway": {"p": "binary_sensor", "name": "Gateway",
                             "device_class": "connectivity", "unique_id": f"{oid}_gateway",
                             "state_topic": f"{base}/bridge/state",
                             "payload_on": "online", "payload_off": "offline"}},
        "qos": qos,
    }


def is_ours(payload: Mapping[str, Any], gateway_id: str, base: str) -> bool:
    """A discovery payload this gateway (this id, this base topic) published."""
    who = payload.get("o")
    if not isinstance(who, Mapping) or who.get("name") != ORIGIN_NAME:
        return False
    ids = payload.get("dev", {}).get("ids") if isinstance(payload.get("dev"), Mapping) else None
    prefix = safe_id(f"rtupoll_{gateway_id}_")
    if not (isinstance(ids, list) and any(isinstance(i, str) and i.startswith(prefix)
                                          for i in ids)):
        return False
    topics = [payload.get("state_topic")]
    cmps = payload.get("cmps")
    if isinstance(cmps, Mapping):
        topics += [c.get("state_topic") for c in cmps.values() if isinstance(c, Mapping)]
    return any(isinstance(t, str) and t.startswith(f"{base}/") for t in topics)
