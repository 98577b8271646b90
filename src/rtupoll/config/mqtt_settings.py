"""What ``poll`` needs to know to publish over MQTT: the broker, topics, and per-device choices.

Built from ``--mqtt URL`` (``mqtt://[USER[:PASS]@]HOST[:PORT][/BASE]``, ``mqtts://`` for
TLS) and from the site file's ``mqtt:`` section, which is checked like the rest of
the file (``file:line: path: message``). Pure: reads the password file, imports no
MQTT library, so a site file is checked the same with or without the ``mqtt`` extra.
"""

from __future__ import annotations

import os
import re
import socket
from collections.abc import Mapping
from dataclasses import field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import unquote, urlsplit

from rtupoll.errors import UsageError
from rtupoll.frozen import frozen

# the gateway's identity in topics and ids (docs/mqtt.md)
ID_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
_NOT_ID = re.compile(r"[^a-z0-9_-]")
BASE_PREFIX = "rtupoll"  # the default base is rtupoll/<gateway_id>


def default_gateway_id(hostname: str | None = None) -> str:
    """The host name, lower-cased, with anything but ``[a-z0-9_-]`` as ``_`` (``rtupoll``
    for a host with no usable name)."""
    name = (hostname if hostname is not None else socket.gethostname()).strip().lower()
    return _NOT_ID.sub("_", name).strip("_")[:64] or "rtupoll"


def check_gateway_id(text: str, what: str = "--mqtt-id") -> str:
    if not ID_PATTERN.match(text):
        raise UsageError(f"{what} {text!r}: a gateway id is 1 to 64 of a-z, 0-9, '_' and "
                         "'-', starting with a letter or digit")
    return text


def default_base(gateway_id: str) -> str:
    return f"{BASE_PREFIX}/{gateway_id}"


if TYPE_CHECKING:
    from rtupoll.config.yamlsrc import Node

DEFAULT_PREFIX = "homeassistant"
PASSWORD_ENV = "RTUPOLL_MQTT_PASSWORD"  # a password for a URL that names only the user
PUBLISH_MODES = ("every_scan", "on_change")
_TOPIC_TEXT = re.compile(r"^[^#+\x00]+$")


@frozen
class DeviceOptions:
    """How one device is published (site file: ``mqtt.devices.NAME``, else the defaults)."""

    publish: str = "every_scan"  # or on_change: only when a value changed, or ...
    max_silence: float = 300.0  # ... at least every this many seconds
    field_topics: bool = False  # also BASE/DEVICE/FIELD, one plain value each
    allow: tuple[str, ...] = ()  # address / baud-rate fields that MQTT may write


@frozen
class MqttSettings:
    host: str
    port: int = 1883
    tls: bool = False
    username: str | None = None
    password: str | None = None
    base_topic: str | None = None  # as given (URL, site file); None: rtupoll/<gateway_id>
    gateway_id: str = field(default_factory=default_gateway_id)  # docs/mqtt.md "Identity"
    client_id: str | None = None
    ca: str | None = None  # TLS: CA bundle (None: the system's)
    cert: str | None = None  # TLS client certificate and key
    key: str | None = None
    qos: int = 0
    retain: bool = False  # retain the state messages (availability and discovery always are)
    discovery: bool = True
    discovery_prefix: str = DEFAULT_PREFIX
    allow_writes: bool = False
    defaults: DeviceOptions = DeviceOptions()
    devices: Mapping[str, DeviceOptions] = field(default_factory=dict)

    @property
    def base(self) -> str:
        """The base topic: as given, else ``rtupoll/<gateway_id>``."""
        return self.base_topic if self.base_topic is not None else default_base(self.gateway_id)

    @property
    def where(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"

    def options(self, device: str) -> DeviceOptions:
        return self.devices.get(device, self.defaults)

    def with_url(self, url: str) -> MqttSettings:
        """``--mqtt URL`` over a site file's section: the URL's broker, and its user and
        base when it names them; the section's other choices stay."""
        u = parse_url(url)
        return replace(self, host=u.host, port=u.port, tls=u.tls,
                       username=u.username if u.username is not None else self.username,
                       password=u.password if u.username is not None else self.password,
                       base_topic=u.base_topic if u.base_topic is not None else self.base_topic)


def parse_url(url: str) -> MqttSettings:
    """``mqtt://[USER[:PASS]@]HOST[:PORT][/BASE]`` (``mqtts://``: TLS, port 8883)."""
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError as exc:
        raise UsageError(f"--mqtt {url}: {exc}") from None
    if parts.scheme not in ("mqtt", "mqtts"):
        raise UsageError(f"--mqtt {url}: expected mqtt://[USER[:PASS]@]HOST[:PORT][/BASE] "
                         "(or mqtts:// for TLS)")
    if not parts.hostname:
        raise UsageError(f"--mqtt {url}: no broker host")
    if parts.query or parts.fragment:
        raise UsageError(f"--mqtt {url}: no '?' or '#' parts (options go in the site file)")
    tls = parts.scheme == "mqtts"
    base = unquote(parts.path.strip("/")) or None
    if base is not None:
        check_topic(base, f"--mqtt {url}: base topic")
    user = unquote(parts.username) if parts.username else None
    password = unquote(parts.password) if parts.password is not None else None
    if user is not None and password is None:
        password = os.environ.get(PASSWORD_ENV)
    return MqttSettings(host=parts.hostname, port=port or (8883 if tls else 1883), tls=tls,
                        username=user, password=password, base_topic=base)


def check_topic(text: str, what: str) -> None:
    """A base topic or prefix: no wildcards, no empty levels, no leading ``$``."""
    if not text or not _TOPIC_TEXT.match(text) or text.startswith("$") or "//" in text \
            or text.startswith("/") or text.endswith("/"):
        raise UsageError(f"{what} {text!r} is not a usable MQTT topic (no '+', '#', empty "
                         "levels or leading '$')")


# ---------------------------------------------------------------------------
# the site file's mqtt: section

_KEYS = {"url", "gateway_id", "client_id", "username", "password_env", "password_file", "tls",
         "qos", "retain", "base", "discovery", "discovery_prefix", "allow_writes", "publish",
         "max_silence", "field_topics", "devices"}
_TLS_KEYS = {"ca", "cert", "key"}
_DEVICE_KEYS = {"publish", "max_silence", "field_topics", "allow"}


def parse_section(node: Node, site_file: Path, devices: Mapping[str, Any]) -> MqttSettings:
    """The ``mqtt:`` section; ``devices``: the site's device configs by name (for
    ``devices:`` keys and their ``allow`` lists). Paths are relative to the site file."""
    m = node.mapping(_KEYS, {"url"})

    def text(key: str, what: str) -> str:
        value = m[key].text()
        try:
            check_topic(value, what)
        except UsageError as exc:
            raise m[key].fail(str(exc)) from None
        return value

    try:
        s = parse_url(m["url"].text())
    except UsageError as exc:
        raise m["url"].fail(str(exc).replace(f"--mqtt {m['url'].text()}: ", "")) from None
    if s.username is not None and s.password is not None and ("password_env" in m
                                                             or "password_file" in m):
        raise m["url"].fail("the URL already holds a password: leave out password_env/_file")
    username = m["username"].text() if "username" in m else s.username
    password = s.password
    if "password_env" in m and "password_file" in m:
        raise m["password_file"].fail("give password_env or password_file, not both")
    if "password_env" in m:
        name = m["password_env"].text()
        if name not in os.environ:
            raise m["password_env"].fail(f"the environment variable {name} is not set")
        password = os.environ[name]
    if "password_file" in m:
        path = site_file.parent / m["password_file"].text()
        try:
            password = path.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise m["password_file"].fail(f"cannot read {path}: {exc.strerror}") from None
    if password is not None and username is None:
        raise (m.get("password_env") or m.get("password_file") or m["url"]).fail(
            "a password without a username: add username (or USER@ in the url)")
    tls: dict[str, str | None] = dict.fromkeys(_TLS_KEYS)
    if "tls" in m:
        for key, sub in m["tls"].mapping(_TLS_KEYS).items():
            path = site_file.parent / sub.text()
            if not path.is_file():
                raise sub.fail(f"{path} does not exist")
            tls[key] = str(path)
        if not s.tls:
            raise m["tls"].fail("TLS files need an mqtts:// url")
    if (tls["cert"] is None) != (tls["key"] is None):
        raise m["tls"].fail("a client certificate needs both cert and key")
    gateway_id = s.gateway_id
    if "gateway_id" in m:
        try:
            gateway_id = check_gateway_id(m["gateway_id"].text(), "")
        except UsageError as exc:
            raise m["gateway_id"].fail(str(exc).strip()) from None
    defaults = _device_options(m, DeviceOptions(), devices, None)
    per_device: dict[str, DeviceOptions] = {}
    if "devices" in m:
        for knode, vnode in m["devices"].items():
            name = knode.text()
            if name not in devices:
                raise knode.fail(f"no device {name!r} in this site file")
            per_device[name] = _device_options(vnode.mapping(_DEVICE_KEYS), defaults, devices,
                                               name)
    return replace(
        s, username=username, password=password,
        client_id=m["client_id"].text() if "client_id" in m else None,
        ca=tls["ca"], cert=tls["cert"], key=tls["key"],
        qos=m["qos"].integer(0, 2) if "qos" in m else 0,
        retain=m["retain"].flag() if "retain" in m else False,
        base_topic=text("base", "base") if "base" in m else s.base_topic,
        gateway_id=gateway_id,
        discovery=m["discovery"].flag() if "discovery" in m else True,
        discovery_prefix=text("discovery_prefix", "discovery_prefix")
        if "discovery_prefix" in m else DEFAULT_PREFIX,
        allow_writes=m["allow_writes"].flag() if "allow_writes" in m else False,
        defaults=defaults, devices=per_device)


def _device_options(m: Mapping[str, Node], base: DeviceOptions, devices: Mapping[str, Any],
                    name: str | None) -> DeviceOptions:
    publish = m["publish"].choice(_mode, list(PUBLISH_MODES)) if "publish" in m \
        else base.publish
    silence = base.max_silence
    if "max_silence" in m:
        silence = m["max_silence"].number()
        if not 1 <= silence <= 86_400:
            raise m["max_silence"].fail(f"{silence:g} s is outside 1..86400 s")
    allow: tuple[str, ...] = ()
    if "allow" in m:
        assert name is not None  # the top level's keys (_KEYS) have no 'allow'
        profile = devices[name].profile
        names = []
        for n in m["allow"].sequence():
            f = n.text()
            if f not in profile.names():
                raise n.fail(f"{profile.id} has no field {f!r}")
            if not profile.field(f).writable:
                raise n.fail(f"{f} is read-only")
            names.append(f)
        allow = tuple(names)
    return DeviceOptions(publish=publish, max_silence=silence,
                         field_topics=m["field_topics"].flag() if "field_topics" in m
                         else base.field_topics, allow=allow)


def _mode(text: str) -> str:
    if text not in PUBLISH_MODES:
        raise ValueError(text)
    return text
