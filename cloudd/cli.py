"""`elasticfog cloud --config F --id ID`: run one cloud daemon (a deployment of the service).

The command parses its options, builds the daemon and runs it in the foreground until SIGINT or
SIGTERM (which drains first: the registry moves this deployment's robots, then it exits). Fault
injection flags override the machine's `fault` settings in fleet.yaml; both can be changed at run
time on the deployment's ctl key. Bad input (config, id, flags) is one line on stderr and exit
code 2, never a traceback.
"""

from __future__ import annotations

import contextlib
import faulthandler
import math
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from common.errors import UserError
from common.logs import DEFAULT_LOG_LEVEL, LOG_LEVEL_ENV, LOG_LEVEL_HELP, logging_to_stderr

if TYPE_CHECKING:  # the wire package imports numpy: only the command itself pays for it
    from common.wire.registry import FaultSpec


def dump_threads_on_sigusr1() -> None:
    """`kill -USR1 <pid>` writes every thread's stack to stderr: what a stuck daemon is doing.
    Skipped when stderr is not a real file (e.g. under a test runner capturing output)."""
    # io.UnsupportedOperation (no fileno) is both a ValueError and an OSError.
    with contextlib.suppress(AttributeError, ValueError, OSError):
        faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)


def fault_from_flags(
    base_delay_ms: float, base_drop: float, stall: bool, delay_ms: float | None, drop: float | None
) -> FaultSpec:
    """The FaultSpec at start: fleet.yaml's values, overridden by the flags given."""
    from common.wire.registry import FaultSpec

    if delay_ms is not None and not (delay_ms >= 0 and math.isfinite(delay_ms)):
        raise UserError(f"--inject-delay-ms {delay_ms:g}: expected a finite number >= 0")
    if drop is not None and not 0 <= drop <= 1:
        raise UserError(f"--inject-drop {drop:g}: expected a probability in [0, 1]")
    return FaultSpec(
        delay_ms=base_delay_ms if delay_ms is None else delay_ms,
        drop=base_drop if drop is None else drop,
        stall=stall,
    )


def cloud(
    config: Path = typer.Option(
        ..., "--config", envvar="ELASTICFOG_CONFIG", help="The fleet's fleet.yaml."
    ),
    deployment_id: str = typer.Option(
        ..., "--id", help="This deployment's id (a cloud machine of fleet.yaml)."
    ),
    inject_delay_ms: float | None = typer.Option(
        None,
        "--inject-delay-ms",
        help="Fault injection: extra delay before every inference and probe reply, ms.",
    ),
    inject_drop: float | None = typer.Option(
        None,
        "--inject-drop",
        help="Fault injection: probability of leaving an inference request unanswered.",
    ),
    log_level: str = typer.Option(
        DEFAULT_LOG_LEVEL, "--log-level", envvar=LOG_LEVEL_ENV, help=LOG_LEVEL_HELP
    ),
) -> None:
    """Run a cloud daemon: serve the model's suffixes to the robots the registry routes here."""
    try:
        with logging_to_stderr(log_level):
            from cloudd.daemon import CloudDaemon
            from common.config import load_fleet
            from common.keys import Role

            cfg = load_fleet(config)
            machine = cfg.machine(deployment_id, role=Role.CLOUD)
            fault = fault_from_flags(
                machine.fault.delay_ms,
                machine.fault.drop,
                machine.fault.stall,
                inject_delay_ms,
                inject_drop,
            )
            daemon = CloudDaemon(cfg, deployment_id, fault=fault)
            dump_threads_on_sigusr1()
            code = daemon.run()
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add `elasticfog cloud` to the root app."""
    app.command("cloud")(cloud)
