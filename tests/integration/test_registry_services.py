"""The registry routes per (robot, service), over real Zenoh on loopback.

A fleet of two services, `detect` and `segment`: edge-1 serves both, edge-2 only `detect`; robot-1
and robot-2 use both, and initial_policy prefers edge-1. robot-1 comes first and is placed on
edge-1 for both; robot-2's `detect` then spreads to edge-2 (placement by load, per service) while
its `segment` can only go to edge-1, so its two services are computed by two deployments. The
deployments are played by `ServicesDeployment`, a cloud daemon's registry-facing half that keeps
its states and epochs per (service, robot), answers a probe or a ctl for the service it names
(an `unknown_service` error reply for one it does not serve) and declares each robot's service key
of that service; the robots by `tests.helpers.registry.FakeRobot` (a token and its route key).

What it shows: the `routes` view has a row per (robot, service) naming its service (and so do
the CLI's JSON rows, its tables a service column, `--service` one service's); every route
change, ctl request and probe names its service; a reroute moves the service it names only; the
`deployments` view has a row per (deployment, service); losing edge-1 moves robot-1's `detect` to
edge-2 and leaves both robots' `segment` with no route (each robot computes it itself); a
register or reroute request for a service the fleet lacks is refused by name while the registry
keeps serving.
"""

from __future__ import annotations

import json
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
import zenoh
from typer.testing import CliRunner

from common import keys
from common.cli import app
from common.config import FleetConfig, fleet_from_dict
from common.keys import Role
from common.models import file_digest
from common.wire import ErrorCode, ErrorReply
from common.wire.registry import (
    CAP_LOCAL_FALLBACK,
    PROTOCOL_VERSION,
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    ProbeReply,
    ProbeRequest,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RouteChange,
)
from common.wire.telemetry import FallbackReason
from tests.helpers import registry as reg
from tests.helpers.registry import (
    BOUND_S,
    CAPABILITIES,
    DEADLINE_S,
    HYSTERESIS_S,
    LEASE_MS,
    WINDOW,
    FakeRobot,
    RunningRegistry,
    ask,
    view,
    wait_logged,
    wait_view,
)
from tests.integration.conftest import find_free_port, loopback_endpoint

peer = reg.peer
start_registry = reg.start_registry

DETECT, SEGMENT = "detect", "segment"
ROBOTS = ("robot-1", "robot-2")


# -- the fleet -----------------------------------------------------------------------------------
def write_services_fleet(tmp_path: Path) -> FleetConfig:
    """Two services (each a small model file: the registry only digests it); edge-1 serves
    both, edge-2 `detect` only; both robots use both and start on edge-1."""
    endpoint = loopback_endpoint(find_free_port())
    models = {}
    for name in (DETECT, SEGMENT):
        models[name] = tmp_path / f"{name}.onnx"
        models[name].write_bytes(f"the registry only reads the digest of {name}".encode())
    data: dict[str, Any] = {
        "fleet": f"t{uuid.uuid4().hex[:8]}",
        "services": {name: {"model": str(path)} for name, path in models.items()},
        "registry": {"endpoint": endpoint, "listen": [endpoint]},
        "machines": {
            "edge-1": {"role": "cloud"},
            "edge-2": {"role": "cloud", "services": [DETECT]},
            "robot-1": {"role": "robot"},
            "robot-2": {"role": "robot"},
        },
        "initial_policy": {
            "robot-1": "robot",
            "robot-2": "robot",
            "edge-1": "service",
            "edge-2": "standby",
        },
        "latency_bound": {
            "stat": "median",
            "seconds": BOUND_S,
            "window": WINDOW,
            "hysteresis_s": HYSTERESIS_S,
        },
        "deadline_s": DEADLINE_S,
        "zenoh": {"lease_ms": LEASE_MS},
    }
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return fleet_from_dict(data, source=path)


def digests(cfg: FleetConfig) -> dict[str, str]:
    """Each service's model digest, as the registry computes it."""
    out = {}
    for name in cfg.services:
        path = cfg.for_service(name).model_path
        assert path is not None
        out[name] = file_digest(path)
    return out


class ServicesDeployment:
    """A cloud daemon of several services, registry-facing: token, probe and ctl per service
    (the epoch rules of `tests.helpers.registry.FakeDeployment`, per (service, robot)), each
    robot's service key of a service declared in service only."""

    def __init__(
        self, session: zenoh.Session, cfg: FleetConfig, name: str, digests: dict[str, str]
    ) -> None:
        self.session = session
        self.fleet = cfg.fleet
        self.name = name
        self.services = cfg.services_of(name)
        self.first = cfg.service_name
        self.digests = digests
        self.cond = threading.Condition()
        self.ctl_log: list[CtlRequest] = []
        self.probed: list[str | None] = []
        self.epochs: dict[tuple[str, str], int] = {}
        self.states: dict[tuple[str, str], DeploymentState] = {}
        self._keys: dict[tuple[str, str], Any] = {}
        self._declared = [
            session.declare_queryable(keys.dep_probe(self.fleet, name), self._on_probe),
            session.declare_queryable(keys.dep_ctl(self.fleet, name), self._on_ctl),
        ]
        self.token = session.liveliness().declare_token(keys.alive_deployment(self.fleet, name))

    def _unknown(self, service: str) -> bytes:
        reason = f"{self.name} does not serve {service!r}; it serves {', '.join(self.services)}"
        return ErrorReply.make(ErrorCode.UNKNOWN_SERVICE, reason).to_wire()

    def _on_probe(self, query: zenoh.Query) -> None:
        with query:
            request = ProbeRequest.from_wire(query.payload.to_bytes() if query.payload else b"")
            service = request.service or self.first
            key = keys.dep_probe(self.fleet, self.name)
            with self.cond:
                self.probed.append(request.service)
                if service not in self.services:
                    query.reply(key, self._unknown(service))
                    return
                reply = ProbeReply(
                    deployment=self.name,
                    protocol_version=PROTOCOL_VERSION,
                    capabilities=CAPABILITIES,
                    service=service,
                    model_digest=self.digests[service],
                    states={r: st for (s, r), st in self.states.items() if s == service},
                    epochs={r: e for (s, r), e in self.epochs.items() if s == service},
                    load=0,
                    capacity=4,
                )
            query.reply(key, reply.to_wire())

    def _on_ctl(self, query: zenoh.Query) -> None:
        with query:
            req = CtlRequest.from_wire(query.payload.to_bytes() if query.payload else b"")
            service = req.service or self.first
            key = keys.dep_ctl(self.fleet, self.name)
            assert req.robot is not None
            with self.cond:
                self.ctl_log.append(req)
                self.cond.notify_all()
                if service not in self.services:
                    query.reply(key, self._unknown(service))
                    return
                at = (service, req.robot)
                known = self.epochs.get(at, 0)
                if req.epoch < known:
                    state, epoch, ok = self.states.get(at), known, False
                elif req.op is CtlOp.SERVICE:
                    self._serve(service, req.robot, req.epoch)
                    state, epoch, ok = DeploymentState.SERVICE, req.epoch, True
                else:
                    self._standby(service, req.robot, req.epoch)
                    state, epoch, ok = DeploymentState.STANDBY, req.epoch, True
                reply = CtlReply(
                    ok=ok,
                    deployment=self.name,
                    op=req.op,
                    robot=req.robot,
                    epoch=epoch,
                    state=state,
                    reason="" if ok else f"stale epoch {req.epoch}: holding {known}",
                    service=service,
                )
            query.reply(key, reply.to_wire())

    def _serve(self, service: str, robot: str, epoch: int) -> None:
        at = (service, robot)
        if at not in self._keys:
            key = keys.svc_infer(self.fleet, service, robot)

            def infer(query: zenoh.Query) -> None:
                with query:
                    query.reply(key, self.name.encode())

            self._keys[at] = self.session.declare_queryable(key, infer, complete=True)
        self.epochs[at] = epoch
        self.states[at] = DeploymentState.SERVICE

    def _standby(self, service: str, robot: str, epoch: int) -> None:
        declared = self._keys.pop((service, robot), None)
        if declared is not None:
            declared.undeclare()
        self.epochs[(service, robot)] = epoch
        self.states[(service, robot)] = DeploymentState.STANDBY

    def wait_ctl(self, what: str, predicate: Callable[[CtlRequest], bool]) -> CtlRequest:
        """The first ctl request received (so far or from now on) matching `predicate`."""
        return wait_logged(self.cond, self.ctl_log, predicate, f"{self.name}: no {what}")

    def die(self) -> None:
        """Vanish like a killed process: the session closes, the token goes with it."""
        self.session.close()


def cli(*args: str) -> tuple[int, str, str]:
    """`elasticfog ARGS` in-process (wide enough that no table cell wraps)."""
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    return result.exit_code, result.stdout, result.stderr


def routes_of(rows: tuple[Any, ...]) -> dict[tuple[str, str | None], str | None]:
    """(robot, service) -> deployment, from the routes view."""
    return {(r.robot, r.service): r.deployment for r in rows}


def serves(service: str, deployment: str | None) -> Callable[[RouteChange], bool]:
    """A route change of `service` to `deployment` (None: the robot computes it itself)."""
    return lambda c: c.service == service and c.deployment == deployment


# -- the tests -----------------------------------------------------------------------------------
def test_routes_are_per_robot_and_service_and_fail_over_per_service(
    tmp_path: Path,
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> None:
    cfg = write_services_fleet(tmp_path)
    registry = start_registry(cfg, db_path=tmp_path / "rib.sqlite")
    sums = digests(cfg)
    edges = {name: ServicesDeployment(peer(cfg), cfg, name, sums) for name in ("edge-1", "edge-2")}
    observer = peer(cfg)
    # robot-1 first: initial_policy puts both its services on edge-1.
    robots = {"robot-1": FakeRobot(peer(cfg), cfg, "robot-1")}
    for service in (DETECT, SEGMENT):
        change = robots["robot-1"].wait_route(f"{service} to edge-1", serves(service, "edge-1"))
        assert change.epoch == 1
    # Then robot-2: placement by load is per service. Its `detect` spreads to edge-2 (edge-1
    # has robot-1's already); its `segment` has edge-1 alone. Two deployments, one robot.
    robots["robot-2"] = FakeRobot(peer(cfg), cfg, "robot-2")
    expected = {
        ("robot-1", DETECT): "edge-1",
        ("robot-1", SEGMENT): "edge-1",
        ("robot-2", DETECT): "edge-2",
        ("robot-2", SEGMENT): "edge-1",
    }
    rows = wait_view(
        observer, cfg, "routes", lambda rows: routes_of(rows) == expected, "a route per service"
    )
    assert {r.epoch for r in rows} == {1}, "each (robot, service) has epochs of its own"
    for service, deployment in ((DETECT, "edge-2"), (SEGMENT, "edge-1")):
        change = robots["robot-2"].wait_route(
            f"{service} to {deployment}", serves(service, deployment)
        )
        assert change.epoch == 1
    # Every ctl request names its service, and edge-2 is never asked about `segment`.
    edges["edge-1"].wait_ctl(
        "service(robot-2, segment)",
        lambda r: (r.op, r.robot, r.service) == (CtlOp.SERVICE, "robot-2", SEGMENT),
    )
    edges["edge-2"].wait_ctl(
        "service(robot-2, detect)",
        lambda r: (r.op, r.robot, r.service) == (CtlOp.SERVICE, "robot-2", DETECT),
    )
    assert all(r.service == DETECT for r in edges["edge-2"].ctl_log), edges["edge-2"].ctl_log
    assert not [r for r in edges["edge-1"].ctl_log if (r.robot, r.service) == ("robot-2", DETECT)]
    assert {DETECT, SEGMENT} <= set(edges["edge-1"].probed), "edge-1 is probed per service"
    assert set(edges["edge-2"].probed) == {DETECT}, "edge-2 is probed for its one service"

    # A row per (deployment, service), each with that service's states.
    deployments = {(d.id, d.service): d for d in view(observer, cfg, "deployments")}
    assert deployments.keys() == {("edge-1", DETECT), ("edge-1", SEGMENT), ("edge-2", DETECT)}
    assert deployments[("edge-1", SEGMENT)].states == {
        "robot-1": DeploymentState.SERVICE,
        "robot-2": DeploymentState.SERVICE,
    }
    assert deployments[("edge-1", DETECT)].states == {"robot-1": DeploymentState.SERVICE}
    assert deployments[("edge-2", DETECT)].states == {"robot-2": DeploymentState.SERVICE}
    robot_rows = {(r.id, r.service): r.deployment for r in view(observer, cfg, "robots")}
    assert robot_rows == expected
    only = view(observer, cfg, "routes", service=SEGMENT)
    assert {r.service for r in only} == {SEGMENT} and len(only) == 2
    assert {e.service for e in view(observer, cfg, "events")} == {DETECT, SEGMENT}
    # The CLI: JSON rows carry their service, the table a service column, --service filters.
    connect = ["--connect", cfg.registry.endpoint, "--fleet", cfg.fleet]
    code, out, err = cli("routes", *connect, "--json")
    assert code == 0, err
    assert {(r["robot"], r["service"]): r["deployment"] for r in json.loads(out)} == expected
    code, out, err = cli("routes", *connect)
    assert code == 0 and "service" in out and SEGMENT in out, (out, err)
    code, out, err = cli("robots", *connect, "--service", DETECT, "--json")
    assert code == 0, err
    assert {(r["id"], r["service"]) for r in json.loads(out)} == {
        ("robot-1", DETECT),
        ("robot-2", DETECT),
    }
    code, _, err = cli("routes", *connect, "--service", "track")
    assert code == 2 and "unknown service 'track'" in err, err

    # edge-1 dies: robot-1's `detect` moves to edge-2; `segment` has nowhere to go, so both
    # robots compute it themselves; robot-2's `detect` stays where it was.
    edges["edge-1"].die()
    moved = robots["robot-1"].wait_route("detect to edge-2", serves(DETECT, "edge-2"))
    assert (moved.epoch, moved.reason) == (2, "deployment_lost")
    for name in ROBOTS:
        local = robots[name].wait_route(f"{name} segment local", serves(SEGMENT, None))
        assert local.epoch == 2 and local.reason.startswith("deployment_lost"), local
    after = {
        ("robot-1", DETECT): "edge-2",
        ("robot-1", SEGMENT): None,
        ("robot-2", DETECT): "edge-2",
        ("robot-2", SEGMENT): None,
    }
    wait_view(observer, cfg, "routes", lambda rows: routes_of(rows) == after, "the failover")
    assert not [c for c in robots["robot-2"].routes if c.service == DETECT and c.epoch > 1]
    edges["edge-2"].wait_ctl(
        "service(robot-1, detect) at epoch 2",
        lambda r: (r.op, r.robot, r.service, r.epoch) == (CtlOp.SERVICE, "robot-1", DETECT, 2),
    )
    # Each service's RIB is a file of its own: the first keeps the configured one.
    assert (tmp_path / "rib.sqlite").is_file() and (tmp_path / "rib.segment.sqlite").is_file()
    assert registry.daemon.planes is not None and len(registry.daemon.planes) == 2


def test_a_service_the_fleet_lacks_is_refused_by_name_and_the_registry_keeps_serving(
    tmp_path: Path,
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> None:
    cfg = write_services_fleet(tmp_path)
    start_registry(cfg)
    sums = digests(cfg)
    for name in ("edge-1", "edge-2"):
        ServicesDeployment(peer(cfg), cfg, name, sums)
    robot = FakeRobot(peer(cfg), cfg, "robot-1")
    for service in (DETECT, SEGMENT):
        robot.wait_route(f"{service} on edge-1", serves(service, "edge-1"))
    session = peer(cfg)

    def register(service: str, robot_id: str = "robot-1") -> RegisterReply:
        request = RegisterRequest(
            role=Role.ROBOT,
            id=robot_id,
            protocol_version=PROTOCOL_VERSION,
            capabilities=(CAP_LOCAL_FALLBACK,),
            service=service,
            model_digest=sums.get(service),
        )
        reply = ask(session, keys.reg_register(cfg.fleet), request.to_wire())
        assert isinstance(reply, RegisterReply), reply
        return reply

    refused = register("track")
    assert not refused.accepted
    assert "'track'" in refused.reason and "'detect', 'segment'" in refused.reason
    # A known service, registered once per service: the route in the reply is that service's.
    accepted = register(SEGMENT)
    assert accepted.accepted and accepted.route is not None
    assert (accepted.route.service, accepted.route.deployment) == (SEGMENT, "edge-1")

    def reroute(service: str | None) -> Any:
        request = RerouteRequest(
            robot="robot-1",
            deployment="edge-1",
            epoch=1,
            reason=FallbackReason.TIMEOUT,
            service=service,
        )
        return ask(session, keys.reg_reroute(cfg.fleet), request.to_wire())

    error = reroute("track")
    assert isinstance(error, ErrorReply) and error.code == ErrorCode.UNKNOWN_SERVICE.value
    assert "'track'" in error.reason and "detect, segment" in error.reason
    # Still serving: a reroute moves the service it names, and that one only.
    moved = reroute(DETECT)
    assert isinstance(moved, RouteChange), moved
    assert (moved.service, moved.deployment, moved.epoch) == (DETECT, "edge-2", 2)
    routes = {r.service: (r.deployment, r.epoch) for r in view(session, cfg, "routes")}
    assert routes == {DETECT: ("edge-2", 2), SEGMENT: ("edge-1", 1)}
    # `segment` has nowhere else to go: its reply is its current route.
    stays = reroute(SEGMENT)
    assert isinstance(stays, RouteChange), stays
    assert (stays.service, stays.deployment, stays.reason) == (SEGMENT, "edge-1", "current route")
    refusals = [e for e in view(session, cfg, "events") if e.kind == "registration_refused"]
    assert len(refusals) == 1 and "'track'" in refusals[0].reason
