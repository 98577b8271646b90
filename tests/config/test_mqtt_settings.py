"""MQTT settings: the --mqtt URL and the site file's mqtt: section, and their mistakes
(rtupoll.config.mqtt_settings)."""

from __future__ import annotations

from pathlib import Path

import pytest
from site_files import site_file

from rtupoll.config.mqtt_settings import parse_url
from rtupoll.config.site import load_site
from rtupoll.errors import ConfigError, UsageError


def test_url_gives_broker_credentials_and_base() -> None:
    s = parse_url("mqtts://gw:p%40ss@broker.lan/site/north")
    assert (s.host, s.port, s.tls, s.username, s.password, s.base) == \
        ("broker.lan", 8883, True, "gw", "p@ss", "site/north")
    plain_url = parse_url("mqtt://10.0.0.2:1884")
    assert (plain_url.port, plain_url.tls, plain_url.base_topic, plain_url.username) == \
        (1884, False, None, None)
    assert plain_url.base == f"rtupoll/{plain_url.gateway_id}"  # the default


def test_url_user_without_password_takes_it_from_the_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RTUPOLL_MQTT_PASSWORD", "from-env")
    assert parse_url("mqtt://gw@h").password == "from-env"


@pytest.mark.parametrize("url, why", [
    ("http://h", "expected mqtt://"),
    ("mqtt://", "no broker host"),
    ("mqtt://h/a/+/b", "not a usable MQTT topic"),
    ("mqtt://h:99999", "Port out of range"),
])
def test_bad_urls_are_one_line(url: str, why: str) -> None:
    with pytest.raises(UsageError, match=why.replace("+", r"\+")):
        parse_url(url)


def test_site_section(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PLANT_MQTT", "s3cret")
    site = load_site(site_file(tmp_path, (
        "mqtt:\n"
        "  url: mqtt://broker.lan/plant\n"
        "  username: gw\n"
        "  password_env: PLANT_MQTT\n"
        "  qos: 1\n"
        "  publish: on_change\n"
        "  max_silence: 60\n"
        "  devices:\n"
        "    tank: {publish: every_scan, allow: [baud_rate], field_topics: true}\n")))
    s = site.mqtt
    assert s is not None
    assert (s.host, s.username, s.password, s.qos, s.base) == ("broker.lan", "gw", "s3cret", 1,
                                                               "plant")
    assert (s.options("air").publish, s.options("air").max_silence) == ("on_change", 60)
    tank = s.options("tank")
    assert (tank.publish, tank.allow, tank.field_topics, tank.max_silence) == \
        ("every_scan", ("baud_rate",), True, 60)
    # a password file, relative to the site file
    (tmp_path / "mqtt-password").write_text("from-file\n")
    other = load_site(site_file(tmp_path, "mqtt:\n  url: mqtt://gw@broker.lan\n"
                                          "  password_file: mqtt-password\n")).mqtt
    assert other is not None and (other.username, other.password) == ("gw", "from-file")
    # --mqtt URL replaces the broker, keeps the section's other choices
    moved = s.with_url("mqtt://other:1999")
    assert (moved.host, moved.port, moved.base, moved.username, moved.qos) == \
        ("other", 1999, "plant", "gw", 1)


@pytest.mark.parametrize("section, where", [
    ("mqtt:\n  url: mqtt://b\n  qso: 1\n", "10: mqtt.qso: unknown key (did you mean 'qos'?)"),
    ("mqtt:\n  url: mqtt://b\n  username: u\n  password_env: NOPE_NOT_SET\n",
     "11: mqtt.password_env: the environment variable NOPE_NOT_SET is not set"),
    ("mqtt:\n  url: mqtt://b\n  username: u\n  password_file: missing.txt\n",
     "11: mqtt.password_file: cannot read"),
    ("mqtt:\n  url: mqtt://b\n  devices:\n    pump: {publish: on_change}\n",
     "11: mqtt.devices.pump: no device 'pump' in this site file"),
    ("mqtt:\n  url: mqtt://b\n  devices:\n    tank: {allow: [level_cm]}\n",
     "11: mqtt.devices.tank.allow[0]: level_cm is read-only"),
    ("mqtt:\n  url: mqtt://b\n  publish: sometimes\n",
     "10: mqtt.publish: 'sometimes' is not one of: every_scan, on_change"),
    ("mqtt:\n  url: ftp://b\n", "9: mqtt.url: expected mqtt://"),
])
def test_site_section_mistakes_are_file_line(tmp_path: Path, section: str, where: str) -> None:
    path = site_file(tmp_path, section)
    with pytest.raises(ConfigError) as err:
        load_site(path)
    assert str(err.value).startswith(f"{path}:{where}")
