"""Options shared by several commands, defined once."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import click

F = TypeVar("F", bound=Callable[..., object])

profiles_option = click.option(
    "--profiles", "profile_dirs", multiple=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Extra profile directory (repeatable; also $RTUPOLL_PROFILES). Searched before "
         "the bundled profiles.")


def format_option(*choices: str) -> Callable[[F], F]:
    return click.option("--format", "fmt", type=click.Choice(list(choices)),
                        default=choices[0], show_default=True, help="Output format.")
