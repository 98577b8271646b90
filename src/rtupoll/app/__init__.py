"""Wiring: the services a command runs, built and handed to each other (above the
services, below cli/)."""
