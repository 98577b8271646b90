"""The names ``io/bus.py`` and ``io/syncbus.py`` still take from here, from their homes
(``port_settings``, ``port_names``, ``own_port``, ``pty_parity``, ``port_diagnosis``).
Nothing else imports this module: the rooms move (issue 50, rooms-move.sh) points the two
drivers' imports at the homes, and removes it, once their concurrent edits are merged."""

from __future__ import annotations

from rtupoll.io.own_port import claim as claim
from rtupoll.io.port_diagnosis import diagnose_gateway as diagnose_gateway
from rtupoll.io.port_diagnosis import diagnose_serial as diagnose_serial
from rtupoll.io.port_names import device_path as device_path
from rtupoll.io.port_names import port_url as port_url
from rtupoll.io.port_settings import PortSettings as PortSettings
from rtupoll.io.pty_parity import line_parity as line_parity
