"""Where the dashboard listens and who may read it: --http and the site file's http:
(rtupoll.config.http_settings)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rtupoll.config.http_settings import HttpSettings, from_options, merge, parse_listen
from rtupoll.config.site import load_site
from rtupoll.errors import ConfigError, UsageError


def test_listen_addresses() -> None:
    assert parse_listen("8080") == ("127.0.0.1", 8080)  # a port alone: loopback
    assert parse_listen(":8080") == ("127.0.0.1", 8080)
    assert parse_listen("0.0.0.0:80") == ("0.0.0.0", 80)
    assert parse_listen("[::1]:8080") == ("::1", 8080)
    for bad in ("host", "1.2.3.4:99999", "", "a:b"):
        with pytest.raises(UsageError):
            parse_listen(bad)


def test_loopback_open_and_guarded() -> None:
    assert HttpSettings("127.0.0.1", 1).warning() == ""
    assert HttpSettings("::1", 1).warning() == ""
    assert HttpSettings("localhost", 1).warning() == ""
    assert "readable by anyone" in HttpSettings("0.0.0.0", 1).warning()
    assert HttpSettings("0.0.0.0", 1, token="12345678").warning() == ""
    assert HttpSettings("192.168.1.5", 1, users={"a": "12345678"}).warning() == ""


def test_the_command_line_over_the_site_file() -> None:
    site = HttpSettings("0.0.0.0", 80, token="site-token", users={"u": "site-pass"})
    assert merge(None, site) is site
    cli = from_options("127.0.0.1:8080", None, ())
    assert merge(cli, site) == HttpSettings("127.0.0.1", 8080, "site-token", {"u": "site-pass"})
    only_token = from_options(None, "cli-token-1", ())
    assert merge(only_token, site) == HttpSettings("0.0.0.0", 80, "cli-token-1",
                                                   {"u": "site-pass"})
    with pytest.raises(UsageError, match="need --http HOST:PORT"):
        merge(only_token, None)
    assert from_options(None, None, ()) is None


def test_the_site_files_http_section(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    body = ("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n    devices:\n"
            "      - {profile: huiwen-aq, address: 3}\n")
    path.write_text("http: 8080\n" + body)
    assert load_site(path).http == HttpSettings("127.0.0.1", 8080)
    path.write_text("http:\n  listen: 0.0.0.0:8080\n  token: a-long-token\n"
                    "  users: {tech: correct-horse}\n" + body)
    assert load_site(path).http == HttpSettings("0.0.0.0", 8080, "a-long-token",
                                                {"tech": "correct-horse"})
    for text, line, message in (
            ("http: nowhere\n", 1, "http: 'nowhere': expected [HOST:]PORT, e.g. "
                                   "127.0.0.1:8080"),
            ("http:\n  listen: 8080\n  token: short\n", 3, "http.token: shorter than 8 "
                                                            "characters"),
            ("http:\n  listen: 8080\n  users: {tech: pw}\n", 3,
             "http.users.tech: the password is shorter than 8 characters"),
            ("http:\n  token: a-long-token\n", 2, "http: missing required key 'listen'")):
        path.write_text(text + body)
        with pytest.raises(ConfigError) as bad:
            load_site(path)
        assert str(bad.value).startswith(f"{path}:{line}: "), str(bad.value)
        assert message.split(": ", 1)[1].split("'")[0] in str(bad.value), str(bad.value)


def test_the_listeners_limits_in_the_site_file_and_on_the_command_line(tmp_path: Path
                                                                       ) -> None:
    from rtupoll.config import http_settings as hs
    assert (hs.HttpSettings("127.0.0.1", 1).header_timeout, hs.IDLE_TIMEOUT,
            hs.MAX_CONNECTIONS) == (10.0, 60.0, 256)
    path = tmp_path / "site.yaml"
    body = ("buses:\n  - port: /dev/ttyUSB0\n    baudrate: 9600\n    devices:\n"
            "      - {profile: huiwen-aq, address: 3}\n")
    path.write_text("http:\n  listen: 8080\n  header_timeout: 2.5\n  idle_timeout: 30\n"
                    "  max_connections: 40\n  hosts: [Dash.Example, '[::1]', 10.0.0.1]\n" + body)
    site = load_site(path).http
    assert site is not None
    assert (site.header_timeout, site.idle_timeout, site.max_connections, site.hosts) == (
        2.5, 30.0, 40, ("dash.example", "::1", "10.0.0.1"))
    # the command line's, where given, over the file's
    cli = from_options(None, None, (), {"idle_timeout": 5.0, "max_connections": None,
                                         "hosts": ()})
    got = merge(cli, site)
    assert got is not None
    assert (got.header_timeout, got.idle_timeout, got.max_connections, got.hosts) == (
        2.5, 5.0, 40, ("dash.example", "::1", "10.0.0.1"))
    for text, message in (("header_timeout: 0", "0 is not a number of seconds"),
                          ("idle_timeout: 4000", "4000 is not a number of seconds"),
                          ("max_connections: 1.5", "expected a whole number"),
                          ("hosts: [a b]", "'a b' is not a host name")):
        path.write_text(f"http:\n  listen: 8080\n  {text}\n" + body)
        with pytest.raises(ConfigError, match=message) as bad:
            load_site(path)
        assert str(bad.value).startswith(f"{path}:3: "), str(bad.value)


def test_the_host_names_a_loopback_listener_answers_to() -> None:
    s = HttpSettings("127.0.0.1", 8080, hosts=("dash.example",))
    for ok in ("localhost", "LOCALHOST.", "app.localhost", "127.0.0.1", "127.1.2.3", "[::1]",
               "::1", "dash.example"):
        assert s.allows_host(ok), ok
    for foreign in ("evil.com", "localhost.evil.com", "10.0.0.1", "", "dash.example.evil",
                    "127.0.0.1.nip.io"):
        assert not s.allows_host(foreign), foreign
