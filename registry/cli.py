"""`elasticfog registry --config F [--db PATH]`: run the registry daemon in the foreground.

The command parses its options, loads the fleet file and runs `registry.daemon.RegistryDaemon`
until SIGINT/SIGTERM (exit 0). A bad config, an unusable RIB file or a listen endpoint already in
use is one line on stderr and exit code 2.
"""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from common.errors import UserError

LOG_LEVEL_ENV = "ELASTICFOG_LOG_LEVEL"
LOG_LEVELS = ("debug", "info", "warning", "error")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def setup_logging(level: str) -> None:
    """Log lines on stderr at `level` (one of LOG_LEVELS)."""
    if level.lower() not in LOG_LEVELS:
        raise UserError(f"--log-level {level!r}: expected one of {', '.join(LOG_LEVELS)}")
    logging.basicConfig(level=level.upper(), format=LOG_FORMAT)


def registry(
    config: Path = typer.Option(..., "--config", "-c", help="The fleet file (fleet.yaml)."),
    db: Path | None = typer.Option(
        None,
        "--db",
        help="sqlite file of the routing information base (default: registry.db of the fleet "
        "file, else <fleet>.rib.sqlite next to it).",
    ),
    log_level: str = typer.Option(
        "info", "--log-level", envvar=LOG_LEVEL_ENV, help="debug, info, warning or error."
    ),
) -> None:
    """Run the registry: the routing information base, the scheduler and the embedded Zenoh
    router. Stops cleanly on Ctrl-C / SIGTERM."""
    # Heavy imports (pydantic, zenoh, the wire codec) where the command runs: `elasticfog --help`
    # must stay fast.
    from common.config import load_fleet
    from registry.daemon import run_registry

    try:
        setup_logging(log_level)
        cfg = load_fleet(config)
        code = run_registry(cfg, db_path=db)
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add `elasticfog registry` to the root app."""
    app.command("registry")(registry)
