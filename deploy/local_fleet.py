"""The daemons of one fleet.yaml as subprocesses on this host, and a session to watch them.

`LocalFleet` puts the runtime's daemons on top of `deploy.procs.ProcessSet`: start them with the
real CLI, wait until each is ready (`deploy.readiness`), and watch them as any other machine of
the fleet would (tokens, probes, ctl, the registry's views, the robots' telemetry); in a TLS fleet
the watching session listens on TLS only and shows the registry's certificate
(`observer_identity`). `write_local_fleet` writes the fleet file it runs.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deploy.procs import (
    WATCH_INTERVAL_S,
    DaemonError,
    DaemonProc,
    ProcessSet,
    StopResult,
    free_tcp_port,
)
from deploy.readiness import TokenWatch, wait_until
from deploy.telemetry_tap import TelemetryTap

if TYPE_CHECKING:
    from common.config import FleetConfig


def merge_into(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """Merge `changes` into `base` in place: nested mappings merge, other values replace."""
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            merge_into(base[key], value)
        else:
            base[key] = value
    return base


def write_local_fleet(
    directory: Path,
    *,
    fleet: str | None = None,
    model: str | None = None,
    port: int | None = None,
    changes: dict[str, Any] | None = None,
    tls: bool = False,
) -> Path:
    """`elasticfog init`'s single-host fleet.yaml with a free registry port and a fleet name of
    its own (two runs on one host never see each other's keys), `changes` merged in, checked
    with `load_fleet`. With `tls`, what `elasticfog init --tls` writes: certificates in
    `directory/certs/`, mutual TLS and access control on every link. Returns the file's path."""
    import uuid

    import yaml

    from common.config import load_fleet
    from common.init_cli import DEFAULT_MODEL, write_fleet
    from common.yaml_files import read_yaml

    path = write_fleet(
        Path(directory),
        port=port or free_tcp_port(),
        fleet=fleet or f"local-{uuid.uuid4().hex[:8]}",
        model=model or DEFAULT_MODEL,
        force=True,
        tls=tls,
    )
    if changes:
        data = read_yaml(path)
        merge_into(data, changes)
        path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
        load_fleet(path)  # a bad change fails here, naming the field
    return path


def link_protocol(cfg: FleetConfig) -> str:
    """The Zenoh protocol of the fleet's links: `tls` in a TLS fleet (nothing listens in
    plaintext), else `tcp`."""
    return "tls" if cfg.tls else "tcp"


def observer_identity(cfg: FleetConfig) -> str | None:
    """Whose certificate a session that watches and drives a fleet shows (this module's, the
    testbed's observer): in a TLS fleet the registry's, since it follows telemetry, reads the
    views and sends ctl, which the access control lets only the registry do; else none."""
    return cfg.registry.id if cfg.tls else None


class LocalFleet:
    """The daemons of one fleet.yaml as subprocesses on this host, and a session to watch them.

    What the demo, the e2e tests and the benchmarks share: start the registry, cloud daemons and
    robots with the real CLI, wait until each is ready (registry: its router accepts connections and
    its liveliness token is up; cloud: its token is up and, if the registry runs, the registry lists
    it as alive; robot: its token), and talk to them as any other machine would — probe and ctl
    keys, the registry's views, the robots' telemetry. The observer session is a peer like the
    daemons, so it keeps seeing the robots and clouds when the registry is gone. `argv0`: the
    command that runs the daemons' CLI (None: this installation's, `deploy.procs.elasticfog_argv`),
    e.g. the `elasticfog` of a virtual environment installed as a robot host installs it.
    """

    def __init__(
        self,
        config: Path,
        workdir: Path,
        *,
        env: dict[str, str] | None = None,
        startup_timeout_s: float = 60.0,
        argv0: Sequence[str] | None = None,
    ) -> None:
        from common.config import load_fleet

        self.argv0 = argv0
        self.config = Path(config)
        self.cfg = load_fleet(self.config)
        self.fleet = self.cfg.fleet
        self.workdir = Path(workdir)
        self.startup_timeout_s = startup_timeout_s
        self.procs = ProcessSet(self.workdir / "logs", env=env)
        # What the fleet owns, released in reverse by `close`: the daemons (entered by `with`),
        # then the observer's resources (session, token watch, taps), each entered as it is
        # made; one that fails to release does not keep the others (the session last) open.
        self._owned = contextlib.ExitStack()
        self._watching = self._owned.enter_context(contextlib.ExitStack())
        self._session: Any = None
        self._tokens: TokenWatch | None = None
        self._restarts: dict[str, int] = {}

    # -- context -----------------------------------------------------------------------------
    def __enter__(self) -> LocalFleet:
        self._owned.enter_context(self.procs)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> list[StopResult]:
        """Stop every daemon (robots first), then release the observer's taps, token watch and
        session, in reverse order of making."""
        try:
            return self.procs.close()  # what `with` entered closes again below: a no-op
        finally:
            self._session = self._tokens = None
            self._owned.close()

    @property
    def registry_host_port(self) -> tuple[str, int]:
        address = self.cfg.registry.endpoint.partition("/")[2]
        host, _, port = address.rpartition(":")
        return host.strip("[]"), int(port)

    @property
    def session(self) -> Any:
        """The observer's Zenoh peer session (opened on first use)."""
        if self._session is None:
            session = self._open_observer_session()
            self._watching.callback(_close_quietly, session)
            self._tokens = self._watching.enter_context(TokenWatch(session, self.fleet))
            self._session = session
        return self._session

    def _open_observer_session(self) -> Any:
        """How the observer's session is opened (a fleet of other identities overrides it); the
        fleet owns what this returns."""
        from common.session import open_session

        return open_session(
            self.cfg,
            identity=observer_identity(self.cfg),
            listen=[f"{link_protocol(self.cfg)}/127.0.0.1:0"],
        )

    @property
    def tokens(self) -> TokenWatch:
        _ = self.session
        assert self._tokens is not None
        return self._tokens

    # -- starting daemons --------------------------------------------------------------------
    def _name(self, base: str) -> str:
        # A daemon started again (registry restart) gets its own log file.
        count = self._restarts.get(base, 0)
        self._restarts[base] = count + 1
        return base if count == 0 else f"{base}.{count}"

    def start_registry(self, *args: str, wait: bool = True) -> DaemonProc:
        """`elasticfog registry --config F [args]`; with `wait`, until it is ready."""
        from common import keys

        proc = self.procs.start(
            self._name("registry"), ["registry", *self._config_args, *args], argv0=self.argv0
        )
        if wait:
            host, port = self.registry_host_port
            wait_until(
                lambda: _tcp_accepting(host, port),
                timeout_s=self.startup_timeout_s,
                what=f"the registry's router on {host}:{port}",
                procs=[proc],
                interval_s=WATCH_INTERVAL_S,
            )
            self.tokens.wait_for(
                [keys.alive_registry(self.fleet, self.cfg.registry.id)],
                timeout_s=self.startup_timeout_s,
                procs=[proc],
            )
        return proc

    def start_cloud(self, cloud_id: str, *args: str) -> DaemonProc:
        """`elasticfog cloud --config F --id ID [args]`, not waited for (see `wait_clouds`)."""
        return self.procs.start(
            self._name(cloud_id),
            ["cloud", *self._config_args, "--id", cloud_id, *args],
            argv0=self.argv0,
        )

    def start_clouds(
        self, deployment_ids: Sequence[str] | None = None, *args: str
    ) -> list[DaemonProc]:
        """Start cloud daemons side by side, then wait until every one is ready."""
        ids = list(self.cfg.deployment_ids if deployment_ids is None else deployment_ids)
        procs = [self.start_cloud(c, *args) for c in ids]
        self.wait_clouds(ids, procs=procs)
        return procs

    def wait_clouds(
        self, deployment_ids: Sequence[str], *, procs: Sequence[DaemonProc] | None = None
    ) -> None:
        """Until each cloud's token is up and, if a registry runs, it lists them as alive."""
        from common import keys

        self.tokens.wait_for(
            [keys.alive_deployment(self.fleet, c) for c in deployment_ids],
            timeout_s=self.startup_timeout_s,
            procs=procs,
        )
        if self.registry_alive():
            wait_until(
                lambda: self._registered(deployment_ids),
                timeout_s=self.startup_timeout_s,
                what=f"the registry to register {', '.join(deployment_ids)}",
                procs=procs,
            )

    def start_robot(
        self,
        robot_id: str,
        *args: str,
        frames: int | None = None,
        telemetry: Path | None = None,
        wait: bool = False,
    ) -> DaemonProc:
        """`elasticfog robot --config F --id ID [--frames N] [--telemetry FILE] [args]`."""
        from common import keys

        cli = ["robot", *self._config_args, "--id", robot_id]
        if frames is not None:
            cli += ["--frames", str(frames)]
        if telemetry is not None:
            cli += ["--telemetry", str(telemetry)]
        proc = self.procs.start(self._name(robot_id), [*cli, *args], argv0=self.argv0)
        if wait:
            self.tokens.wait_for(
                [keys.alive_robot(self.fleet, robot_id)],
                timeout_s=self.startup_timeout_s,
                procs=[proc],
            )
        return proc

    @property
    def _config_args(self) -> list[str]:
        return ["--config", str(self.config)]

    # -- watching ----------------------------------------------------------------------------
    def tap(
        self, robot_id: str, on_record: Callable[[dict[str, Any]], None] | None = None
    ) -> TelemetryTap:
        """Follow `robot_id`'s telemetry from now on (declare before starting the robot)."""
        from common import keys

        tap = TelemetryTap(self.session, keys.tele(self.fleet, robot_id), on_record)
        self._watching.callback(tap.close)
        return tap

    def registry_alive(self) -> bool:
        from common import keys

        return keys.alive_registry(self.fleet, self.cfg.registry.id) in self.tokens.alive

    def query(self, key: str, payload: bytes | None = None, *, timeout_s: float = 2.0) -> list[Any]:
        """Every decoded reply to a get on `key` (ErrorReply included); no reply: []."""
        from common.wire import decode

        kwargs: dict[str, Any] = {"timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = payload
        out = []
        for reply in self.session.get(key, **kwargs):
            if reply.ok is not None:
                out.append(decode(reply.ok.payload.to_bytes()))
        return out

    def view(self, name: str, *, timeout_s: float = 2.0) -> list[Any]:
        """The rows of the registry's view `name` (deployments, robots, routes, events...)."""
        from common import keys
        from common.wire.registry import RIB_VIEW_REPLIES

        expected = RIB_VIEW_REPLIES[name]
        for message in self.query(keys.rib(self.fleet, name), timeout_s=timeout_s):
            if isinstance(message, expected):
                return list(message.rows)  # type: ignore[attr-defined]
            raise DaemonError(f"registry view {name}: unexpected reply {message!r}")
        raise DaemonError(f"no reply from the registry on view {name}")

    def route(self, robot_id: str) -> Any | None:
        """The registry's route row for `robot_id` (None if it has none)."""
        for row in self.view("routes"):
            if row.robot == robot_id:
                return row
        return None

    def _registered(self, deployment_ids: Sequence[str]) -> bool:
        alive = {row.id for row in self.view("deployments", timeout_s=1.0) if row.alive}
        return all(c in alive for c in deployment_ids)

    def probe(self, deployment: str, *, timeout_s: float = 2.0) -> Any:
        """The ProbeReply of `deployment` (DaemonError if it does not answer)."""
        from common import keys
        from common.wire.registry import ProbeReply, ProbeRequest

        request = ProbeRequest(sender="observer", sent_at=time.time()).to_wire()
        key = keys.dep_probe(self.fleet, deployment)
        for message in self.query(key, request, timeout_s=timeout_s):
            if isinstance(message, ProbeReply):
                return message
            raise DaemonError(f"probe of {deployment}: unexpected reply {message!r}")
        raise DaemonError(f"no probe reply from {deployment}")

    def ctl(self, deployment: str, request: Any, *, timeout_s: float = 2.0) -> Any:
        """Send a CtlRequest to `deployment`; its CtlReply (DaemonError if none or refused)."""
        from common import keys
        from common.wire.registry import CtlReply

        key = keys.dep_ctl(self.fleet, deployment)
        for message in self.query(key, request.to_wire(), timeout_s=timeout_s):
            if isinstance(message, CtlReply) and message.ok:
                return message
            raise DaemonError(f"ctl {request.op.value} to {deployment} refused: {message!r}")
        raise DaemonError(f"no ctl reply from {deployment}")

    def set_fault(
        self, deployment: str, *, delay_ms: float = 0.0, drop: float = 0.0, stall: bool = False
    ) -> Any:
        """Fault injection at run time on `deployment`'s ctl key."""
        from common.wire.registry import CtlOp, CtlRequest, FaultSpec

        fault = FaultSpec(delay_ms=delay_ms, drop=drop, stall=stall)
        return self.ctl(deployment, CtlRequest(op=CtlOp.FAULT, fault=fault, sender="observer"))

    # -- stopping ----------------------------------------------------------------------------
    def kill(self, name: str) -> float:
        """SIGKILL daemon `name` (its latest incarnation); returns the wall-clock instant."""
        proc = self.latest(name)
        at = time.time()
        proc.kill()
        return at

    def latest(self, base: str) -> DaemonProc:
        """The most recently started daemon called `base` (or `base.N` after restarts)."""
        for proc in reversed(self.procs.procs):
            if proc.name == base or proc.name.startswith(base + "."):
                return proc
        raise KeyError(base)


def _close_quietly(session: Any) -> None:
    """Close the observer's session; a session that fails to close is left to the process."""
    with contextlib.suppress(Exception):
        session.close()


def _tcp_accepting(host: str, port: int) -> bool:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.2)
        return sock.connect_ex((host, port)) == 0
