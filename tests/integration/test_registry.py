"""The registry daemon over real Zenoh on loopback: the registry runs in-process (its `run()` in a
thread, its own embedded router on a free port); deployments and the robot are played by the
test with real peer sessions speaking common/wire (`FakeDeployment` answers probe and ctl with the
cloud daemon's epoch rules and declares the service key; `FakeRobot` holds a token, publishes
telemetry and probe reports, and follows its route key).

What it shows: registration and the initial route (initial_policy's deployment); a lost token
moves the robot to the standby under epoch+1 with the route published; a bound violation held
past the hysteresis moves it, and steady telemetry then keeps it there (no flapping);
consecutive timeouts and a reroute request move it at once; drain; a refused registration
(wrong model digest, protocol) is never routed to; a restarted registry restores routes and
epochs from sqlite and schedules again; the anycast repair of a deployment found serving a robot
routed elsewhere.

The test fleet (the daemon in a thread, the played deployments and robot) is
`tests.helpers.registry`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from common import keys
from common.config import FleetConfig
from common.wire import decode
from common.wire.registry import (
    CtlOp,
    DeploymentState,
    DrainReply,
    DrainRequest,
    RerouteRequest,
    RouteChange,
)
from deploy.readiness import wait_until
from tests.helpers import registry as reg
from tests.helpers.registry import (
    DEADLINE_S,
    FRAME_PERIOD_S,
    HYSTERESIS_S,
    QUERY_TIMEOUT_S,
    ROBOT,
    SWITCH_SLACK_S,
    TEST_PARAMS,
    WAIT_S,
    WINDOW,
    FakeDeployment,
    FakeRobot,
    Fleet,
    RunningRegistry,
    ask,
    model_digest,
    pace,
    view,
    wait_view,
)

# The registry fixtures (tests.helpers.registry).
fleet = reg.fleet
peer = reg.peer
routed = reg.routed
start_registry = reg.start_registry


def test_registration_and_initial_route_to_the_service_machine(
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> None:
    _, cfg = fleet
    start_registry(cfg)
    digest = model_digest(cfg)
    # The standby registers first: the robot must still go to initial_policy's service machine.
    edge2 = FakeDeployment(peer(cfg), cfg, "edge-2", digest=digest)
    robot = FakeRobot(peer(cfg), cfg)
    edge1 = FakeDeployment(peer(cfg), cfg, "edge-1", digest=digest)
    change = robot.wait_route("assigned", lambda c: c.deployment is not None)
    assert (change.deployment, change.epoch, change.reason) == ("edge-1", 1, "initial")
    edge1.wait_ctl("service(1)", lambda r: r.op is CtlOp.SERVICE and r.epoch == 1)
    assert robot.infer() == ["edge-1"], "the service key is edge-1's alone"
    assert not edge2.ctl_log, "the standby was never asked to serve"

    observer = peer(cfg)
    [route] = view(observer, cfg, "routes")
    assert (route.robot, route.deployment, route.epoch) == (ROBOT, "edge-1", 1)
    assert route.reason == "initial: local -> edge-1"
    deployments = {d.id: d for d in view(observer, cfg, "deployments")}
    assert deployments.keys() == {"edge-1", "edge-2"}
    assert all(d.alive and d.model_digest == digest for d in deployments.values())
    assert deployments["edge-1"].states == {ROBOT: DeploymentState.SERVICE}
    [robot_row] = view(observer, cfg, "robots")
    assert (robot_row.id, robot_row.alive, robot_row.deployment, robot_row.epoch) == (
        ROBOT,
        True,
        "edge-1",
        1,
    )
    assert robot_row.extra["state"] == "service"
    kinds = [e.kind for e in view(observer, cfg, "events")]
    assert {"deployment_up", "robot_up", "route"} <= set(kinds)


def test_a_lost_token_switches_to_the_standby_at_once(routed: Fleet) -> None:
    t0 = time.monotonic()
    routed.edges["edge-1"].die()
    change = routed.robot.wait_route("to edge-2", lambda c: c.deployment == "edge-2")
    took_ms = (time.monotonic() - t0) * 1000
    assert (change.epoch, change.reason) == (2, "deployment_lost")
    assert took_ms < 2000, f"reroute after the token loss took {took_ms:.0f} ms"
    routed.edges["edge-2"].wait_ctl("service(2)", lambda r: r.op is CtlOp.SERVICE and r.epoch == 2)
    # edge-2 declared the key before its ack; the declaration reaches the robot's session
    # asynchronously, so the first query may still find no queryable.
    wait_until(
        lambda: routed.robot.infer() == ["edge-2"], timeout_s=WAIT_S, what="edge-2 answering"
    )
    [route] = view(routed.observer, routed.cfg, "routes")
    assert (route.deployment, route.epoch) == ("edge-2", 2)
    edge1 = {d.id: d for d in view(routed.observer, routed.cfg, "deployments")}["edge-1"]
    assert not edge1.alive


def test_a_bound_violation_switches_after_the_hysteresis_and_does_not_flap(routed: Fleet) -> None:
    robot, stop = routed.robot, threading.Event()
    # Steady and within the bound: no move, even with a standby probing as well.
    for _ in range(3):
        robot.probed("edge-1", 0.01)
        robot.probed("edge-2", 0.01)
    pace(stop, 40, lambda i: robot.frame_done("edge-1", 0.02))
    assert [c.epoch for c in robot.routes] == [1]

    # edge-1 slows down far past the bound; edge-2 probes well.
    slow_s = 0.3
    violated_at = None
    for i in range(200):
        robot.frame_done("edge-1", slow_s)
        if i % 5 == 0:
            robot.probed("edge-2", 0.01)
        if i == WINDOW // 2:
            violated_at = time.monotonic()  # the window's median is slow from here on
        if robot.routes[-1].epoch > 1 or stop.wait(FRAME_PERIOD_S):
            break
    change = robot.wait_route("to edge-2", lambda c: c.deployment == "edge-2")
    assert violated_at is not None
    took_s = time.monotonic() - violated_at
    assert (change.epoch, change.reason) == (2, "bound_violation")
    assert HYSTERESIS_S <= took_s <= HYSTERESIS_S + SWITCH_SLACK_S, f"switched after {took_s:.2f} s"

    # Steady afterwards: edge-2 good, edge-1 still slow. The robot stays on edge-2.
    def steady(i: int) -> None:
        robot.frame_done("edge-2", 0.02)
        if i % 5 == 0:
            robot.probed("edge-1", slow_s)
            robot.probed("edge-2", 0.01)

    pace(stop, 100, steady)
    assert [c.deployment for c in robot.routes] == ["edge-1", "edge-2"], robot.routes
    moves = [e for e in view(routed.observer, routed.cfg, "events") if e.kind == "route"]
    assert len(moves) == 2, moves


def test_consecutive_timeouts_reroute_at_once(routed: Fleet) -> None:
    robot = routed.robot
    for _ in range(TEST_PARAMS.timeout_count):
        robot.frame_done(None, DEADLINE_S, fallback=True, reason="timeout")
    change = robot.wait_route("to edge-2", lambda c: c.deployment == "edge-2", timeout_s=2.0)
    assert (change.epoch, change.reason) == (2, "timeouts")


def test_a_reroute_request_is_answered_with_the_new_route(routed: Fleet) -> None:
    request = RerouteRequest(
        robot=ROBOT, deployment="edge-1", epoch=1, reason="timeouts", consecutive_timeouts=2
    )
    reply = ask(routed.observer, keys.reg_reroute(routed.cfg.fleet), request.to_wire())
    assert isinstance(reply, RouteChange)
    assert (reply.deployment, reply.epoch) == ("edge-2", 2)
    # An old request (the robot has moved since) changes nothing.
    again = ask(routed.observer, keys.reg_reroute(routed.cfg.fleet), request.to_wire())
    assert (again.deployment, again.epoch, again.reason) == ("edge-2", 2, "current route")


def test_drain_moves_the_robots_then_replies(routed: Fleet) -> None:
    request = DrainRequest(deployment="edge-1", reason="SIGTERM")
    reply = ask(routed.observer, keys.reg_drain(routed.cfg.fleet), request.to_wire())
    assert isinstance(reply, DrainReply)
    assert (reply.ok, reply.moved) == (True, (ROBOT,))
    # By the time the reply arrives the robot is served elsewhere and edge-1 stood down.
    assert routed.robot.infer() == ["edge-2"]
    routed.edges["edge-1"].wait_ctl("standby", lambda r: r.op is CtlOp.STANDBY and r.epoch == 2)
    change = routed.robot.wait_route("to edge-2", lambda c: c.deployment == "edge-2")
    assert (change.epoch, change.reason) == (2, "drain")


def test_drain_with_nowhere_to_go_says_so(routed: Fleet) -> None:
    routed.edges["edge-2"].die()
    wait_view(
        routed.observer,
        routed.cfg,
        "deployments",
        lambda rows: not {d.id: d for d in rows}["edge-2"].alive,
        "edge-2 gone",
    )
    reply = ask(
        routed.observer,
        keys.reg_drain(routed.cfg.fleet),
        DrainRequest(deployment="edge-1").to_wire(),
    )
    assert isinstance(reply, DrainReply) and not reply.ok and reply.moved == ()
    assert ROBOT in reply.reason


def test_a_refused_registration_is_logged_and_never_routed_to(
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
    caplog: pytest.LogCaptureFixture,
) -> None:
    _, cfg = fleet
    caplog.set_level(logging.INFO, logger="registry")
    start_registry(cfg, restore_grace_s=0.5)
    FakeDeployment(peer(cfg), cfg, "edge-1", digest="0" * 64)
    FakeDeployment(peer(cfg), cfg, "edge-2", digest=model_digest(cfg), protocol_version=99)
    robot = FakeRobot(peer(cfg), cfg)
    observer = peer(cfg)
    events = wait_view(
        observer,
        cfg,
        "events",
        lambda rows: sum(e.kind == "registration_refused" for e in rows) == 2,
        "two refusals",
    )
    refused = [e for e in events if e.kind == "registration_refused"]
    reasons = {e.deployment: e.reason for e in refused}
    assert "model" in reasons["edge-1"] and "same model" in reasons["edge-1"]
    assert "protocol 99" in reasons["edge-2"]
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("refused cloud edge-1" in line and "model" in line for line in lines), lines
    rows = {d.id: d for d in view(observer, cfg, "deployments")}
    assert not rows["edge-1"].alive and "model" in rows["edge-1"].extra["refused"]
    # Past the grace time the robot would take any deployment there is: there is none.
    assert not _wait_for_route_event(observer, cfg, 1.5)
    assert robot.routes == []


def _wait_for_route_event(session: zenoh.Session, cfg: FleetConfig, timeout_s: float) -> bool:
    """Whether any route change is published within `timeout_s`."""
    seen = threading.Event()
    sub = session.declare_subscriber(keys.route_all(cfg.fleet), lambda s: seen.set())
    try:
        return seen.wait(timeout_s)
    finally:
        sub.undeclare()


def test_a_restarted_registry_restores_routes_from_sqlite_and_schedules_again(
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> None:
    _, cfg = fleet
    first = start_registry(cfg)
    digest = model_digest(cfg)
    edges = {n: FakeDeployment(peer(cfg), cfg, n, digest=digest) for n in ("edge-1", "edge-2")}
    robot = FakeRobot(peer(cfg), cfg)
    robot.wait_route("to edge-1", lambda c: c.deployment == "edge-1")
    assert first.stop() < 2.0

    start_registry(cfg)  # same file, same port: the peers reconnect by themselves
    again = edges["edge-1"].wait_ctl(
        "the restored route re-asserted", lambda r: r.reason == "restore"
    )
    assert (again.op, again.epoch) == (CtlOp.SERVICE, 1), "same epoch: nothing new was issued"
    observer = peer(cfg)
    [route] = view(observer, cfg, "routes")
    assert (route.deployment, route.epoch) == ("edge-1", 1)

    edges["edge-1"].die()
    change = robot.wait_route("to edge-2", lambda c: c.deployment == "edge-2")
    assert (change.epoch, change.reason) == (2, "deployment_lost")


def test_a_deployment_found_serving_a_robot_routed_elsewhere_stands_down(
    routed: Fleet, peer: Callable[[FleetConfig], zenoh.Session]
) -> None:
    cfg = routed.cfg
    stray = FakeDeployment(peer(cfg), cfg, "edge-3", digest=model_digest(cfg), serving=(ROBOT,))
    req = stray.wait_ctl("standby", lambda r: r.op is CtlOp.STANDBY)
    assert (req.robot, req.epoch) == (ROBOT, 1)
    assert routed.robot.infer() == ["edge-1"]


def test_stop_is_quick_and_closes_everything(
    fleet: tuple[Path, FleetConfig], start_registry: Callable[..., RunningRegistry]
) -> None:
    _, cfg = fleet
    registry = start_registry(cfg)
    took_s = registry.stop()
    assert took_s < 2.0, f"stop took {took_s:.2f} s"
    assert registry.daemon.session is None and registry.daemon.rib is None


def test_views_filter_and_a_wildcard_query_gets_every_view(routed: Fleet) -> None:
    cfg, observer = routed.cfg, routed.observer
    assert len(view(observer, cfg, "events", limit=1)) == 1
    assert view(observer, cfg, "routes", robot="robot-9") == ()
    assert [d.id for d in view(observer, cfg, "deployments", deployment="edge-2")] == ["edge-2"]
    replies = observer.get(keys.rib_all(cfg.fleet), timeout=QUERY_TIMEOUT_S)
    samples = [r.ok for r in replies if r.ok is not None]
    got = {str(s.key_expr): type(decode(s.payload.to_bytes())).__name__ for s in samples}
    assert got == {
        keys.rib(cfg.fleet, "deployments"): "DeploymentsView",
        keys.rib(cfg.fleet, "robots"): "RobotsView",
        keys.rib(cfg.fleet, "routes"): "RoutesView",
        keys.rib(cfg.fleet, "events"): "EventsView",
        keys.rib(cfg.fleet, "profiles"): "ProfilesView",
    }
