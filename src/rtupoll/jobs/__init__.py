"""The work done on a bus: polling and its statistics, scan, writes, commissioning."""
