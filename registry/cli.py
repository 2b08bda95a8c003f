"""`elasticfog registry --config F [--db PATH]`: run the registry daemon in the foreground.

The command parses its options, loads the fleet file and runs `registry.daemon.RegistryDaemon`
until SIGINT/SIGTERM (exit 0). A bad config, an unusable RIB file or a listen endpoint already in
use is one line on stderr and exit code 2.
"""

from __future__ import annotations

from pathlib import Path

import typer

from common.errors import UserError
from common.logs import DEFAULT_LOG_LEVEL, LOG_LEVEL_ENV, LOG_LEVEL_HELP, logging_to_stderr


def registry(
    config: Path = typer.Option(..., "--config", "-c", help="The fleet file (fleet.yaml)."),
    db: Path | None = typer.Option(
        None,
        "--db",
        help="sqlite file of the routing information base (default: registry.db of the fleet "
        "file, else <fleet>.rib.sqlite next to it).",
    ),
    metrics_port: int | None = typer.Option(
        None,
        "--metrics-port",
        metavar="PORT",
        help="Serve Prometheus metrics on this port (/metrics); default: registry.metrics.port, "
        "else off.",
    ),
    log_level: str = typer.Option(
        DEFAULT_LOG_LEVEL, "--log-level", envvar=LOG_LEVEL_ENV, help=LOG_LEVEL_HELP
    ),
) -> None:
    """Run the registry: the routing information base, the scheduler and the embedded Zenoh
    router. Stops cleanly on Ctrl-C / SIGTERM."""
    # Heavy imports (pydantic, zenoh, the wire codec) where the command runs: `elasticfog --help`
    # must stay fast.
    from common.config import load_fleet
    from common.metrics import check_port
    from registry.daemon import RegistryDaemon

    try:
        with logging_to_stderr(log_level):
            check_port(metrics_port)
            cfg = load_fleet(config)
            daemon = RegistryDaemon(cfg, db_path=db, metrics_port=metrics_port)
            code = daemon.run()
            daemon.exit_if_abandoned(code)
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add `elasticfog registry` to the root app."""
    app.command("registry")(registry)
