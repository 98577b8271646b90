"""Listening to a bus rtupoll does not own: ``rtupoll sniff``.

- ``port``: the tap, a serial port opened so that nothing is ever sent;
- ``capfile``: capture files (pcapng, link type 250 RTAC serial) written and read;
- ``model``: what was seen per unit: health, reply times, latest fields, "looks like";
- ``lines``: the one-line-per-transaction text (no rich);
- ``render``: the live table (rich).

The splitting of the byte stream into frames and transactions is protocol logic and
lives, sans-IO, in ``rtupoll.rtu.stream``.
"""
