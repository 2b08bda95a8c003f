"""`elasticfog routes|deployments|robots|events|watch`: the registry's routing state, queried over
Zenoh from any host that can reach the registry.

Each command opens a Zenoh *client* session to the registry's endpoint (`registry.endpoint` of
`--config F`, or `--connect ENDPOINT` with `--fleet NAME`), queries one read-only view
(`ef/<fleet>/rib/<view>`) and prints it as a table, or as plain JSON on stdout with `--json` (a
list of row objects). `watch` redraws a live table of the robots (their deployment, its state,
the epoch, the latency window against the bound, the cut chosen) until Ctrl-C. Routing is per
(robot, service): every row names its service (a column when the rows hold several), and
`--service NAME` shows one service's rows only.

An unreachable endpoint, or a router where no registry answers within `--timeout`, is one line
naming the endpoint and what to start there (`common.session.start_registry_hint`) on stderr and
exit code 2; so is a refusal from the registry.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from common.errors import UserError

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig
    from common.wire.registry import (
        RibQuery,
    )

VIEW_TIMEOUT_S = 3.0
# How long a client keeps trying to reach the endpoint (a registry restarting is back within it;
# a refused connection is not worth minutes of retries).
CONNECT_TIMEOUT_S = 1.0
WATCH_INTERVAL_S = 1.0
DEFAULT_EVENTS = 50
MAX_VIEW_BYTES = 16 * 1024 * 1024


@dataclass(frozen=True)
class Target:
    """Where the registry is: its endpoint and fleet (and the fleet file, for TLS settings)."""

    endpoint: str
    fleet: str
    cfg: FleetConfig | None = None


def resolve_target(config: Path | None, connect: str | None, fleet: str | None = None) -> Target:
    """The registry to ask: `--connect` wins over the file's endpoint; the fleet name comes from
    `--fleet`, else the file, else `default`. UserError when neither is given or one is bad."""
    # Imports where a command runs (pydantic, zenoh, the wire codec): `elasticfog --help` must
    # stay fast.
    from pydantic import TypeAdapter, ValidationError

    from common.config import Endpoint, load_fleet
    from common.yaml_files import format_validation_error

    cfg = load_fleet(config) if config is not None else None
    if connect is not None:
        try:
            endpoint = TypeAdapter(Endpoint).validate_python(connect)
        except ValidationError as exc:
            raise UserError(f"--connect: {format_validation_error(exc)}") from None
    elif cfg is not None:
        endpoint = cfg.registry.endpoint
    else:
        raise UserError("give --config FILE (the fleet file) or --connect ENDPOINT")
    from common import keys

    name = fleet if fleet is not None else (cfg.fleet if cfg is not None else keys.DEFAULT_FLEET)
    keys.validate_id(name, "--fleet")
    return Target(endpoint=endpoint, fleet=name, cfg=cfg)


class RegistryClient:
    """A client session to the registry's router, for its read-only views. Close it (or use it
    as a context manager): a session left open at exit hangs the process."""

    def __init__(
        self,
        target: Target,
        *,
        timeout_s: float = VIEW_TIMEOUT_S,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
    ) -> None:
        from common.config import CLI_IDENTITY
        from common.session import open_session

        self.target = target
        self.timeout_s = timeout_s
        # In a TLS fleet the CLI shows its own read-only certificate (`cli.tls`), never a host's.
        self.session: zenoh.Session = open_session(
            target.cfg,
            mode="client",
            listen=[],
            connect=[target.endpoint],
            connect_timeout_s=connect_timeout_s,
            identity=CLI_IDENTITY,
        )

    def __enter__(self) -> RegistryClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the session."""
        self.session.close()

    def view(self, name: str, query: RibQuery | None = None) -> tuple[Any, ...]:
        """The rows of view `name` (keys.RIB_VIEWS); UserError naming the endpoint when no
        registry answers in time or it refuses."""
        import zenoh

        from common import keys
        from common.session import start_registry_hint, zenoh_error_text
        from common.wire import ErrorReply, WireError, decode
        from common.wire.registry import RIB_VIEW_REPLIES

        key = keys.rib(self.target.fleet, name)
        expected = RIB_VIEW_REPLIES[name]
        where = f"the registry of fleet {self.target.fleet!r} at {self.target.endpoint}"
        payload = query.to_wire() if query is not None else None
        try:
            replies = self.session.get(key, payload=payload, timeout=self.timeout_s)
            for reply in replies:
                if reply.ok is None:
                    continue
                message = decode(
                    reply.ok.payload.to_bytes(),
                    expect=(expected, ErrorReply),
                    max_bytes=MAX_VIEW_BYTES,
                )
                if isinstance(message, ErrorReply):
                    raise UserError(f"{where} refused the {name} view: {message.reason}")
                rows: tuple[Any, ...] = message.rows  # type: ignore[attr-defined]
                return rows
        except zenoh.ZError as exc:
            raise UserError(f"cannot query {where}: {zenoh_error_text(exc)}") from None
        except WireError as exc:
            raise UserError(f"{where} sent an unreadable {name} view: {exc}") from None
        raise UserError(
            f"no reply from {where} within {self.timeout_s:g} s on {key}: a router answers but "
            f"no registry of this fleet; {start_registry_hint(self.target.cfg)}"
        )


def fetch_view(
    target: Target, name: str, query: RibQuery | None = None, *, timeout_s: float = VIEW_TIMEOUT_S
) -> tuple[Any, ...]:
    """One view's rows through a short-lived client session (see `RegistryClient.view`)."""
    with RegistryClient(target, timeout_s=timeout_s) as client:
        return client.view(name, query)


# -- commands --------------------------------------------------------------------------------------
CONFIG_OPTION = typer.Option(
    None, "--config", "-c", help="The fleet file: its registry.endpoint and fleet name."
)
CONNECT_OPTION = typer.Option(
    None, "--connect", help="The registry's endpoint instead of --config, e.g. tcp/10.0.0.5:7447."
)
FLEET_OPTION = typer.Option(
    None, "--fleet", help="Fleet name with --connect (default: the file's, else 'default')."
)
JSON_OPTION = typer.Option(False, "--json", help="Print plain JSON (a list of rows) on stdout.")
TIMEOUT_OPTION = typer.Option(
    VIEW_TIMEOUT_S, "--timeout", min=0.1, help="Seconds to wait for the registry's answer."
)
SERVICE_OPTION = typer.Option(
    None, "--service", help="Only this service's rows (default: every service's)."
)


def _query(service: str | None, **filters: Any) -> RibQuery | None:
    """The view's filters (None: none), or exit 2 naming a bad value."""
    from common.wire import WireError
    from common.wire.registry import RibQuery

    if service is None and not filters:
        return None
    for option, fields in (("--robot", filters), ("--service", {**filters, "service": service})):
        try:
            query = RibQuery(**fields)
        except WireError as exc:
            typer.echo(f"error: {option}: {exc}", err=True)
            raise typer.Exit(2) from None
    return query


def _show(
    name: str,
    config: Path | None,
    connect: str | None,
    fleet: str | None,
    as_json: bool,
    timeout_s: float,
    query: RibQuery | None = None,
) -> None:
    try:
        target = resolve_target(config, connect, fleet)
        rows = fetch_view(target, name, query, timeout_s=timeout_s)
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    if as_json:
        from common.wire import to_jsonable

        typer.echo(json.dumps([to_jsonable(r) for r in rows], indent=2))
        return
    console = Console()
    if not rows:
        console.print(f"no {name} known to the registry of fleet {target.fleet}")
        return
    from registry.views_render import TABLES

    console.print(TABLES[name](rows, time.time()))


def routes(
    config: Path | None = CONFIG_OPTION,
    connect: str | None = CONNECT_OPTION,
    fleet: str | None = FLEET_OPTION,
    as_json: bool = JSON_OPTION,
    timeout: float = TIMEOUT_OPTION,
    service: str | None = SERVICE_OPTION,
) -> None:
    """Which deployment serves each robot (for each service), under which epoch, since when
    and why."""
    _show("routes", config, connect, fleet, as_json, timeout, _query(service))


def deployments(
    config: Path | None = CONFIG_OPTION,
    connect: str | None = CONNECT_OPTION,
    fleet: str | None = FLEET_OPTION,
    as_json: bool = JSON_OPTION,
    timeout: float = TIMEOUT_OPTION,
    service: str | None = SERVICE_OPTION,
) -> None:
    """Every deployment the registry knows (a row per service it serves): alive, load, its
    state for each robot, its model."""
    _show("deployments", config, connect, fleet, as_json, timeout, _query(service))


def robots(
    config: Path | None = CONFIG_OPTION,
    connect: str | None = CONNECT_OPTION,
    fleet: str | None = FLEET_OPTION,
    as_json: bool = JSON_OPTION,
    timeout: float = TIMEOUT_OPTION,
    service: str | None = SERVICE_OPTION,
) -> None:
    """Every robot (a row per service it uses): its deployment and epoch, its latency window
    against the bound, its cut."""
    _show("robots", config, connect, fleet, as_json, timeout, _query(service))


def events(
    config: Path | None = CONFIG_OPTION,
    connect: str | None = CONNECT_OPTION,
    fleet: str | None = FLEET_OPTION,
    as_json: bool = JSON_OPTION,
    timeout: float = TIMEOUT_OPTION,
    limit: int = typer.Option(DEFAULT_EVENTS, "--limit", min=1, help="Newest events to show."),
    robot: str | None = typer.Option(None, "--robot", help="Only this robot's events."),
    service: str | None = SERVICE_OPTION,
) -> None:
    """The registry's event log (every transition, with its reason), oldest first."""
    _show(
        "events",
        config,
        connect,
        fleet,
        as_json,
        timeout,
        _query(service, robot=robot, limit=limit),
    )


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set `stop` (the loop ends at its next wait) instead of killing mid-query."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def watch(
    config: Path | None = CONFIG_OPTION,
    connect: str | None = CONNECT_OPTION,
    fleet: str | None = FLEET_OPTION,
    interval: float = typer.Option(
        WATCH_INTERVAL_S, "--interval", min=0.1, help="Seconds between refreshes."
    ),
    count: int = typer.Option(
        0, "--count", min=0, help="Stop after this many refreshes (0: until Ctrl-C)."
    ),
    timeout: float = TIMEOUT_OPTION,
    service: str | None = SERVICE_OPTION,
) -> None:
    """A live table of the robots: deployment, state, epoch, latency window vs bound, cut."""
    from rich.live import Live

    from registry.views_render import watch_screen

    stop = threading.Event()
    query = _query(service)
    try:
        target = resolve_target(config, connect, fleet)
        client = RegistryClient(target, timeout_s=timeout)
    except UserError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(exc.exit_code) from None
    where = f"fleet {target.fleet} at {target.endpoint}"
    with client, _stop_on_signals(stop):
        try:
            rows = client.view("robots", query)
        except UserError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(exc.exit_code) from None
        error: str | None = None
        shown = 0
        with Live(watch_screen(where, rows, None, time.time()), auto_refresh=False) as live:
            while True:
                shown += 1
                live.update(watch_screen(where, rows, error, time.time()), refresh=True)
                if (count and shown >= count) or stop.wait(interval):
                    break
                try:
                    rows, error = client.view("robots", query), None
                except UserError as exc:
                    # Keep the last table; the registry may be restarting.
                    error = str(exc)


def register(app: typer.Typer) -> None:
    """Add `routes`, `deployments`, `robots`, `events` and `watch` to the root app."""
    app.command("routes")(routes)
    app.command("deployments")(deployments)
    app.command("robots")(robots)
    app.command("events")(events)
    app.command("watch")(watch)
