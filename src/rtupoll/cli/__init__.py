"""The ``rtupoll`` command: a lazy click group and the one place errors become exit codes.

Subcommands live in their own modules and are imported only when run, so a
one-shot ``rtupoll read`` does not pay for the simulator or the live table.
"""

from __future__ import annotations

import importlib
import sys
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

    def resolve_command(self, ctx: click.Context, args: list[str]
                        ) -> tuple[str | None, click.Command | None, list[str]]:
        name = args[0] if args else ""
        if name and not name.startswith("-") and name not in COMMANDS:
            import difflib

            hint = difflib.get_close_matches(name, COMMANDS, n=1)
            raise click.UsageError(f"no command {name!r}"
                                   + (f" (did you mean {hint[0]!r}?)" if hint else ""), ctx)
        return super().resolve_command(ctx, args)

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
    """The console script: usage mistakes are one line too, like every other error."""
    try:
        code = cli.main(args=argv, prog_name="rtupoll", standalone_mode=False)
    except click.exceptions.NoArgsIsHelpError as exc:  # plain 'rtupoll': the help
        click.echo(exc.ctx.get_help() if exc.ctx else str(exc))
        sys.exit(0)
    except click.exceptions.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx else "rtupoll"
        click.echo(f"rtupoll: {exc.format_message()} (see '{where} --help')", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("rtupoll: interrupted", err=True)
        sys.exit(130)
    sys.exit(code if isinstance(code, int) else 0)
