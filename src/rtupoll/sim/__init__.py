"""The simulator: virtual RS-485 devices built from the same profiles the client uses.

No one here has hardware, and neither do most users on their first day, so every
command is exercised against this package: ``values`` (how fields start and move),
``device`` (one profile's register map and quirks), ``faults`` (what goes wrong, when),
``engine`` (request bytes -> reply bytes or silence), ``server`` (pty / RTU-over-TCP with
wire timing and a tap), ``scenario`` (devices, pins, options and faults from YAML or the
command line), ``consistent`` (values that agree with each other), ``replay`` (the
devices of a capture) and ``runner`` (``simulated_bus``/``simulated_lines``: buses
running in a background thread, for ``poll --simulate`` and tests). The same engine
serves ``rtupoll.sim.virtual.VirtualBus``, in-process and in virtual time.

Nothing is imported here, so ``import rtupoll.sim.runner`` pays only for what it uses.
"""
