"""MQTT commands checked before anything is sent: set, get, the protected fields, a
result's status (rtupoll.outputs.mqtt_commands)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.site import BusConfig, from_specs
from rtupoll.errors import RefusedError, UsageError
from rtupoll.outputs.mqtt_commands import WRITES_OFF, failed, plan_get, plan_set, protected


def banner() -> BusConfig:
    return from_specs("/dev/null", [("banner-ez-array", 5)]).buses[0]


def test_set_is_refused_while_writes_are_off() -> None:
    with pytest.raises(RefusedError, match="writes over MQTT are off"):
        plan_set(banner().devices[0], b'{"measurement_1_mode": "TBB"}', writes_on=False)
    assert failed(RefusedError(WRITES_OFF)) == {"status": "refused", "exit_code": 8,
                                                "error": WRITES_OFF}


def test_a_results_status_is_its_error_classs_word_as_the_docs_list_them() -> None:
    """``status`` in a command's result comes from the error class (``errors.py``, beside
    its exit code): every word the docs list, with its exit code, and "error" for the
    rest."""
    import re

    from rtupoll import errors

    docs = (Path(__file__).parents[2] / "docs" / "mqtt.md").read_text(encoding="utf-8")
    listed = docs.split("(`status`: ", 1)[1].split(")", 1)[0]
    said = {word: int(code) for word, code in re.findall(r"`(\w+)` (\d+)", listed)}
    classes = [c for c in vars(errors).values()
               if isinstance(c, type) and issubclass(c, errors.RtupollError)]
    owned = {c.status: c.exit_code for c in classes if "status" in c.__dict__}
    assert owned == {**said, "error": 1}
    assert failed(errors.EncodeError("x"))["status"] == "refused"  # a subclass: its base's
    assert failed(errors.ConfigError("x"))["status"] == "error"
    assert failed(errors.DeviceException(2, unit=1))["status"] == "exception"


@pytest.mark.parametrize("payload, error, why", [
    (b'{"measurement_1": 3}', RefusedError, "measurement_1 is read-only"),
    (b'{"measurement_1_mode": "NOPE"}', RefusedError, "'NOPE' is not one of"),
    (b'{"slave_address": 9}', RefusedError, "the device's own address"),
    (b'{"nonesuch": 1}', UsageError, "has no field 'nonesuch'"),
    (b"[1, 2]", UsageError, "expected a JSON object"),
    (b"{not json", UsageError, "not JSON"),
])
def test_set_checks_everything_before_sending(payload: bytes, error: type[Exception],
                                              why: str) -> None:
    with pytest.raises(error, match=why):
        plan_set(banner().devices[0], payload, writes_on=True)


def test_address_and_baud_fields_need_a_per_field_allowance() -> None:
    radar = from_specs("/dev/null", [("radar-level", 4)]).buses[0].devices[0]
    p = radar.profile
    assert protected(p, p.field("baud_rate")) == "the device's baud rate"
    assert protected(p, p.field("slave_address")) == "the device's own address"
    with pytest.raises(RefusedError, match=r"allow: \[baud_rate\]"):
        plan_set(radar, b'{"baud_rate": 19200}', writes_on=True)
    (op,) = plan_set(radar, b'{"baud_rate": 19200}', writes_on=True, allow=["baud_rate"])
    assert (op.field.name, op.words) == ("baud_rate", (192,))


def test_get_takes_nothing_a_list_or_fields() -> None:
    dev = banner().devices[0]
    assert plan_get(dev, b"") is None and plan_get(dev, b"{}") is None
    assert [f.name for f in plan_get(dev, b'["emitter_channels"]') or []] == ["emitter_channels"]
    assert [f.name for f in plan_get(dev, b'{"fields": ["measurement_1"]}') or []] == \
        ["measurement_1"]
    with pytest.raises(RefusedError, match="never polled"):
        plan_get(dev, b'["analog_1_peak"]')
