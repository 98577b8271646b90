"""Every bundled profile's Home Assistant discovery, every field of it, writes on: the
names a person sees, the device classes HA converts by, what is enabled by default.

The device classes, units and state classes below are Home Assistant's own tables
(``homeassistant/components/sensor/const.py``, ``DEVICE_CLASS_UNITS`` and
``DEVICE_CLASS_STATE_CLASSES``, 2025.4) for the classes rtupoll announces: an entity
outside them is one HA warns about in its log and keeps out of long-term statistics.
The real consumer of the templates (Jinja2 against real state messages) is
``test_ha_templates.py``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from rtupoll.config.library import load_one
from rtupoll.config.paths import bundled_dir
from rtupoll.config.site import from_specs
from rtupoll.model.profile import Poll
from rtupoll.outputs import homeassistant as ha

M, T, TI = "measurement", "total", "total_increasing"
ANY = {M, T, TI}
# device class -> (units HA accepts, state classes HA accepts)
HA_CLASSES: dict[str, tuple[set[str | None], set[str]]] = {
    "temperature": ({"°C", "°F", "K"}, {M}),
    "humidity": ({"%"}, {M}),
    "carbon_dioxide": ({"ppm"}, {M}),
    "volatile_organic_compounds_parts": ({"ppm", "ppb"}, {M}),
    "volatile_organic_compounds": ({"µg/m³"}, {M}),
    "pm25": ({"µg/m³"}, {M}), "pm10": ({"µg/m³"}, {M}), "pm1": ({"µg/m³"}, {M}),
    "voltage": ({"µV", "mV", "V", "kV", "MV"}, {M}),
    "current": ({"mA", "A"}, {M}),
    "power": ({"mW", "W", "kW", "MW", "GW", "TW"}, {M}),
    "apparent_power": ({"VA", "kVA"}, {M}),
    "reactive_power": ({"var", "kvar"}, {M}),
    "power_factor": ({"%", None}, {M}),
    "energy": ({"Wh", "kWh", "MWh", "GWh", "TWh", "J", "kJ", "MJ", "GJ"}, {T, TI}),
    "frequency": ({"Hz", "kHz", "MHz", "GHz"}, {M}),
    "pressure": ({"Pa", "hPa", "kPa", "bar", "cbar", "mbar", "mmHg", "inHg", "psi"}, {M}),
    "distance": ({"mm", "cm", "m", "km", "in", "ft", "yd", "mi"}, ANY),
    "illuminance": ({"lx"}, {M}),
    "duration": ({"d", "h", "min", "s", "ms"}, ANY),
    "volume": ({"L", "mL", "m³", "ft³", "gal"}, {T, TI}),
    "volume_storage": ({"L", "mL", "m³", "ft³", "gal"}, {M}),
    "volume_flow_rate": ({"m³/h", "L/min", "L/h", "L/s", "gal/min"}, {M}),
    "sound_pressure": ({"dB", "dBA"}, {M}),
    "signal_strength": ({"dB", "dBm"}, {M}),
    "irradiance": ({"W/m²"}, {M}),
    "conductivity": ({"S/cm", "mS/cm", "µS/cm"}, {M}),
    "speed": ({"m/s", "km/h", "mph", "kn", "ft/s", "mm/s"}, {M}),
    "wind_speed": ({"m/s", "km/h", "mph", "kn", "ft/s", "Beaufort"}, {M}),
}
# classes HA converts the value of (to the user's units, or one the user picks); a
# difference must never carry one: +1.5 °C of correction would be 34.7 °F
CONVERTING = {"temperature", "voltage", "current", "power", "energy", "pressure",
              "distance", "duration", "volume", "volume_storage", "volume_flow_rate",
              "power_factor", "volatile_organic_compounds_parts", "conductivity", "speed",
              "wind_speed"}

PROFILES = sorted(p.stem for p in bundled_dir().glob("*.yaml"))


def discovery(pid: str) -> tuple[Any, dict[str, Any]]:
    """The profile and its discovery with every field it lets a poll read (not the
    ``poll: never`` ones), every writable one a control."""
    profile = load_one(pid, [])
    site = from_specs("/dev/null", [(pid, profile.addresses.default)], check_serial=False)
    bus, dev = next(site.devices())
    fields = tuple(f for f in profile.fields if f.poll is not Poll.NEVER)
    dev = dataclasses.replace(dev, fields=fields)
    controls = {f.name: f.writable for f in fields}
    return profile, ha.device_config(dev, bus, gateway_id="gw", base="site", topic="dev",
                                     controls=controls, qos=0)


@pytest.mark.parametrize("pid", PROFILES)
def test_every_entity_name_is_distinct_and_more_than_a_unit(pid: str) -> None:
    profile, cfg = discovery(pid)
    names = [c["name"] for c in cfg["cmps"].values()]
    squashed = [n.casefold().replace(" ", "") for n in names]
    assert len(set(squashed)) == len(squashed), sorted(n for n in names
                                                       if names.count(n) > 1)
    units = {f.unit.casefold().replace(" ", "") for f in profile.fields if f.unit}
    assert not units & set(squashed), sorted(units & set(squashed))
    assert all(n and n == n.strip() for n in names)
    # the names are the titles: the field's, a flag's after it, a control's with "setting"
    for f in profile.fields:
        if f.name in cfg["cmps"]:
            assert cfg["cmps"][f.name]["name"] == f.title


@pytest.mark.parametrize("pid", PROFILES)
def test_device_classes_are_ones_home_assistant_handles_right(pid: str) -> None:
    profile, cfg = discovery(pid)
    by_name = {f.name: f for f in profile.fields}
    for cid, c in cfg["cmps"].items():
        cls = c.get("device_class")
        field = by_name.get(cid)
        where = f"{pid}.{cid}"
        if c["p"] != "sensor" or cls in (None, "enum", "timestamp"):
            assert "state_class" not in c or cls is None, where
            continue
        assert cls in HA_CLASSES, where
        units, states = HA_CLASSES[cls]
        assert c.get("unit_of_measurement") in units, (where, c.get("unit_of_measurement"))
        assert c["state_class"] in states, (where, c["state_class"])
        assert field is not None and not (field.difference and cls in CONVERTING), where
    for f in profile.fields:
        c = cfg["cmps"].get(f.name)
        if c is None or c["p"] != "sensor":
            continue
        if f.difference:  # a correction, an offset: its unit, never a class
            assert "device_class" not in c, f"{pid}.{f.name}"
        if "power_factor" in f.name:
            assert c["device_class"] == "power_factor", f"{pid}.{f.name}"
        if f.name.endswith("_today") and c.get("device_class") == "energy":
            # from 0 each day: a drop is HA's new cycle, never energy returned
            assert c["state_class"] == "total_increasing", f"{pid}.{f.name}"


def test_corrections_offsets_and_magnitudes_are_no_temperatures() -> None:
    _, room = discovery("xy-md02")
    corr = room["cmps"]["temperature_correction"]
    assert (corr["unit_of_measurement"], corr["state_class"]) == ("°C", "measurement")
    assert "device_class" not in corr and "device_class" not in room["cmps"][
        "humidity_correction"]
    assert room["cmps"]["temperature"]["device_class"] == "temperature"
    assert "device_class" not in room["cmps"]["temperature_correction_set"]
    _, rover = discovery("renogy-rover")  # |T| with a below-zero flag beside it
    assert "device_class" not in rover["cmps"]["controller_temperature"]
    _, meter = discovery("eastron-sdm630")
    pf = meter["cmps"]["total_power_factor"]
    assert pf["device_class"] == "power_factor" and "unit_of_measurement" not in pf


@pytest.mark.parametrize("pid", PROFILES)
def test_only_last_seen_is_disabled_by_default(pid: str) -> None:
    _, cfg = discovery(pid)
    disabled = {cid for cid, c in cfg["cmps"].items() if c.get("enabled_by_default") is False}
    assert disabled == {"_last_seen"}
    assert cfg["cmps"]["_last_seen"]["entity_category"] == "diagnostic"
    assert "enabled_by_default" not in cfg["cmps"]["_status"]  # changes only on a change
