"""Modbus TCP (and RTU-over-TCP) gateway: rtupoll owns the RS-485 line and shares it.

- ``mbap``: the MBAP codec, sans-IO (a TCP byte stream -> requests; replies -> bytes);
- ``rtutcp``: the same for RTU frames over TCP;
- ``pdu``: what a request PDU asks for (function, table, range), its checks, replies;
- ``settings``: ``ServeConfig``, from ``--serve*`` options or a site file's ``serve:``;
- ``access``: who may ask what (networks, read-only, broadcasts, address/baud registers);
- ``turns``: fair turns on the line between the poller and the clients;
- ``cache``: answers reads from what the poller read lately (``--serve-cache``);
- ``clients``: per-client statistics;
- ``server``: the asyncio listener and the request worker for one bus;
- ``service``: the ``rtupoll.jobs.services.Service`` that ``rtupoll poll`` runs;
- ``footer``: the live table's lines; ``metrics``: a Prometheus collector;
- ``options``: ``rtupoll poll``'s ``--serve*`` options.

Only ``settings`` is imported by the pure configuration code; nothing here imports
pymodbus (requests reach the wire through ``rtupoll.io.bus``).
"""
