"""The `elasticfog` command line.

The root app is assembled from the `elasticfog.commands` entry points declared in pyproject.toml:
each package registers its own commands, so `common` never imports the daemons. Only this module
exits the process; a `UserError` anywhere becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import inspect
import sys
from importlib.metadata import (
    EntryPoint,
    PackageNotFoundError,
    distribution,
    entry_points,
    version,
)

import typer
from rich.console import Console

from common.errors import UserError

ENTRY_POINT_GROUP = "elasticfog.commands"
# typer coerces a parameter's value through a pydantic TypeAdapter unless it is already a bool.
# The root's `--help` flag is unset (None) whenever a subcommand runs, so `elasticfog routes --help`
# would import pydantic (~0.1 s) just for it; False from the default map is a bool, taken as is.
ROOT_DEFAULTS = {"help": False, "version": False}
PACKAGE = "elasticfog"

app = typer.Typer(
    name="elasticfog",
    help="Elastic split computing for fog and cloud robotics over Zenoh.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"default_map": ROOT_DEFAULTS},
)


def package_version() -> str:
    """The installed package's version (pyproject.toml's, through the package metadata)."""
    try:
        return version(PACKAGE)
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"{PACKAGE} {package_version()}")
        raise typer.Exit()


@app.callback()
def root(
    show_version: bool = typer.Option(
        False,
        "--version",
        "-V",
        callback=_print_version,
        is_eager=True,
        help="Print the version and exit.",
    ),
) -> None:
    """Elastic split computing for fog and cloud robotics over Zenoh."""


def _command_entry_points() -> list[EntryPoint]:
    """The `elasticfog.commands` entry points, read from this package's own metadata (reading
    every installed distribution's, as `entry_points(group=...)` does, took ~4 ms of a start
    that must stay fast); every one of them when run from a tree that was never installed."""
    try:
        found = distribution(PACKAGE).entry_points.select(group=ENTRY_POINT_GROUP)
    except PackageNotFoundError:
        found = entry_points(group=ENTRY_POINT_GROUP)
    return sorted(found, key=lambda e: e.name)


def _register_commands() -> None:
    # Each module imports only what its options need; heavy imports wait for the command to run
    # (`elasticfog --help` must stay fast, tests/unit/test_cli_startup.py).
    for ep in _command_entry_points():
        ep.load()(app)


def as_paragraphs(text: str) -> str:
    """A docstring's help as paragraphs: the line breaks inside a paragraph are the source's
    wrapping, so they become spaces and the terminal wraps the text at its own width (a
    command list showed "... through phases of an / emulated robot")."""
    paragraphs = [" ".join(p.split()) for p in inspect.cleandoc(text).split("\n\n")]
    return "\n\n".join(p for p in paragraphs if p)


def _unwrap_help(group: typer.Typer) -> None:
    """Every command's and group's help under `group` as paragraphs."""
    for command in group.registered_commands:
        text = command.help or (inspect.getdoc(command.callback) if command.callback else None)
        if text:
            command.help = as_paragraphs(text)
    for sub in group.registered_groups:
        if isinstance(sub.help, str):
            sub.help = as_paragraphs(sub.help)
        if sub.typer_instance is not None:
            info = sub.typer_instance.info
            if isinstance(info.help, str):
                info.help = as_paragraphs(info.help)
            _unwrap_help(sub.typer_instance)


_register_commands()
_unwrap_help(app)


def main() -> None:
    """Console-script entry point."""
    try:
        app(standalone_mode=True)
    except UserError as exc:
        Console(stderr=True).print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        sys.exit(exc.exit_code)
