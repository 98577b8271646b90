"""The live dashboard: ``poll --http`` for one gateway, ``rtupoll web --mqtt`` for a fleet.

``settings`` (pure) and ``options`` (click) are imported by the commands; ``server``,
``service`` and ``fleet`` import aiohttp (the ``web`` extra) only when they run.
"""
