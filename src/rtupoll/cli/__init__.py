"""The ``rtupoll`` command: a lazy click group and the one place errors become exit codes.

Subcommands live in their own modules and are imported only when run, so a
one-shot ``rtupoll read`` does not pay for the simulator or the live table.
"""

from __future__ import annotations

import importlib
from typing import Any

import click

from rtupoll.errors import RtupollError

# command name -> "module:attribute", imported on first use
COMMANDS: dict[str, tuple[str, str]] = {
    "poll": ("rtupoll.cli.poll:poll", "Poll devices and show decoded readings live."),
    "read": ("rtupoll.cli.read:read", "Read fields (or raw registers) from one device once."),
    "write": ("rtupoll.cli.write:write", "Write fields (or raw registers), then read back."),
    "set-address": ("rtupoll.cli.address:set_address", "Give a device a new address, verified."),
    "scan": ("rtupoll.cli.scan:scan", "Find and identify the devices on a bus."),
    "guess": ("rtupoll.cli.guess:guess", "Rank interpretations of an unknown device's registers."),
    "decode": ("rtupoll.cli.decode:decode", "Decode captured RTU frames."),
    "simulate": ("rtupoll.cli.simulate:simulate", "Serve simulated devices on a pty or TCP."),
    "profiles": ("rtupoll.cli.profiles:profiles", "List, show and check device profiles."),
}

EXIT_CODES = """\b
Exit codes:
  0  success
  2  bad arguments, profile or configuration
  3  port cannot be opened (missing, busy, no permission)
  4  no response from the device
  5  the device answered with a Modbus exception
  6  verification failed (a write did not take effect)
  7  garbled reply (CRC error, truncated or malformed frame)
  8  refused before sending (read-only field, value out of range, address taken)
  9  poll --once: one or more devices failed
  130 interrupted
"""


class LazyGroup(click.Group):
    def invoke(self, ctx: click.Context) -> Any:
        """Every command runs through here, so this is the one place errors become exit codes."""
        try:
            return super().invoke(ctx)
        except RtupollError as exc:
            click.echo(f"rtupoll: {exc}", err=True)
            raise click.exceptions.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            click.echo("rtupoll: interrupted", err=True)
            raise click.exceptions.Exit(130) from None

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        module, _, attr = COMMANDS[cmd_name][0].partition(":")
        command = getattr(importlib.import_module(module), attr)
        assert isinstance(command, click.Command)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # list commands without importing them
        with formatter.section("Commands"):
            formatter.write_dl([(name, COMMANDS[name][1]) for name in self.list_commands(ctx)])


@click.group(cls=LazyGroup, epilog=EXIT_CODES,
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rtupoll")
def cli() -> None:
    """Modbus RTU devices on RS-485 buses: poll, read, write, readdress, scan.

    Device knowledge comes from YAML profiles (see 'rtupoll profiles list').
    Devices are written PROFILE@ADDRESS, e.g. net-irnet-pro@1.
    """


def main(argv: list[str] | None = None) -> Any:
    """The console script."""
    return cli.main(args=argv, prog_name="rtupoll")
