"""A site file for the tests of a site file's sections: ``site_file(tmp_path, mqtt)``.

One bus, ``plant`` (tcp://127.0.0.1:5020, 9600 baud), with two devices, ``air``
(huiwen-aq@3) and ``tank`` (radar-level@4), followed by ``mqtt`` (the text of a
section, e.g. ``"mqtt:\\n  host: broker.lan\\n"``; "" for none)."""

from __future__ import annotations

from pathlib import Path


def site_file(tmp_path: Path, mqtt: str) -> Path:
    """``tmp_path / "site.yaml"``, written: the bus above, then ``mqtt``."""
    path = tmp_path / "site.yaml"
    path.write_text(
        "buses:\n"
        "  - name: plant\n"
        "    port: tcp://127.0.0.1:5020\n"
        "    baudrate: 9600\n"
        "    devices:\n"
        "      - {name: air, profile: huiwen-aq, address: 3}\n"
        "      - {name: tank, profile: radar-level, address: 4}\n" + mqtt)
    return path
