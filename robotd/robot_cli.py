"""Commands of this package (filled in as the package grows)."""

import typer


def register(app: typer.Typer) -> None:
    """Add this package's commands to the root app."""
