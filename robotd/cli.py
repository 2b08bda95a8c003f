"""The `sim` entry point: the offline policy simulator (`robot` registers from robotd.robot_cli)."""

from __future__ import annotations

import typer

from robotd import sim_cli


def register(app: typer.Typer) -> None:
    """Add this package's commands to the root app."""
    sim_cli.register(app)
