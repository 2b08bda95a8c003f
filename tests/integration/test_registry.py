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

The helpers here are reused by test_registry_views.py and test_registry_input.py.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from common import keys
from common.config import FleetConfig, fleet_from_dict
from common.models import file_digest
from common.session import open_session
from common.wire import decode
from common.wire.registry import (
    CAP_CTL,
    CAP_INFER,
    CAP_PROBE,
    PROTOCOL_VERSION,
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    DrainReply,
    DrainRequest,
    ProbeReply,
    ProbeRequest,
    RerouteRequest,
    RibQuery,
    RouteChange,
)
from common.wire.telemetry import ProbeReport, TelemetryRecord
from deploy.procs import wait_until
from registry.daemon import RegistryDaemon
from registry.scheduler import SchedulerParams
from tests.integration.conftest import find_free_port, loopback_endpoint

SERVICE = "vision"
ROBOT = "robot-1"
WAIT_S = 10.0
QUERY_TIMEOUT_S = 3.0
LEASE_MS = 1000
BOUND_S = 0.1
HYSTERESIS_S = 0.3
WINDOW = 5
DEADLINE_S = 0.5
FRAME_PERIOD_S = 0.02
"""The fake robot's frame period (50 fps): fills a window well within the hysteresis."""
SWITCH_SLACK_S = 1.0
"""Beyond the hysteresis: the scheduler's tick and the switch's ctl round trips, on 2 cores."""
TEST_PARAMS = SchedulerParams(min_dwell_s=0.5, improve_hold_s=1.0, recovery_s=1.0)
CAPABILITIES = (CAP_INFER, CAP_PROBE, CAP_CTL)


# -- the fleet -----------------------------------------------------------------------------------
def write_fleet(tmp_path: Path, **overrides: Any) -> tuple[Path, FleetConfig]:
    """A fleet.yaml for a registry on a free loopback port: edge-1 (service), edge-2 (standby),
    robot-1; the model is a small file (the registry only digests it)."""
    endpoint = loopback_endpoint(find_free_port())
    model = tmp_path / "model.onnx"
    model.write_bytes(b"the registry only reads this file's digest")
    data: dict[str, Any] = {
        "fleet": f"t{uuid.uuid4().hex[:8]}",
        "service": SERVICE,
        "model": str(model),
        "registry": {"endpoint": endpoint, "listen": [endpoint]},
        "machines": {
            "edge-1": {"role": "cloud"},
            "edge-2": {"role": "cloud"},
            ROBOT: {"role": "robot"},
        },
        "initial_policy": {ROBOT: "robot", "edge-1": "service", "edge-2": "standby"},
        "latency_bound": {
            "stat": "median",
            "seconds": BOUND_S,
            "window": WINDOW,
            "hysteresis_s": HYSTERESIS_S,
        },
        "deadline_s": DEADLINE_S,
        "zenoh": {"lease_ms": LEASE_MS},
    }
    data.update(overrides)
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, fleet_from_dict(data, source=path)


def model_digest(cfg: FleetConfig) -> str:
    assert cfg.model_path is not None
    return file_digest(cfg.model_path)


class RunningRegistry:
    """A RegistryDaemon whose `run()` runs in a thread (signals are the main thread's)."""

    def __init__(self, cfg: FleetConfig, **kwargs: Any) -> None:
        kwargs.setdefault("params", TEST_PARAMS)
        self.cfg = cfg
        self.daemon = RegistryDaemon(cfg, **kwargs)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="registry", daemon=True)

    def _run(self) -> None:
        try:
            self.daemon.run()
        except BaseException as exc:
            self.error = exc

    def start(self) -> RunningRegistry:
        self.thread.start()
        started = threading.Thread(target=lambda: self.daemon.ready.wait(WAIT_S))
        started.start()
        started.join()
        if not self.daemon.ready.is_set():
            pytest.fail(f"the registry did not start within {WAIT_S} s: {self.error!r}")
        return self

    def stop(self) -> float:
        """Stop it; returns how long that took (s)."""
        t0 = time.monotonic()
        self.daemon.stop()
        self.thread.join(WAIT_S)
        assert not self.thread.is_alive(), "the registry did not stop"
        assert self.error is None, f"the registry failed: {self.error!r}"
        return time.monotonic() - t0


@pytest.fixture
def fleet(tmp_path: Path) -> tuple[Path, FleetConfig]:
    """(fleet.yaml, its config)."""
    return write_fleet(tmp_path)


@pytest.fixture
def start_registry() -> Iterator[Callable[..., RunningRegistry]]:
    """`start_registry(cfg, **daemon_kwargs)`: a running registry, stopped at teardown."""
    running: list[RunningRegistry] = []

    def start(cfg: FleetConfig, **kwargs: Any) -> RunningRegistry:
        reg = RunningRegistry(cfg, **kwargs).start()
        running.append(reg)
        return reg

    try:
        yield start
    finally:
        for reg in running:
            if reg.thread.is_alive():
                reg.stop()


@pytest.fixture
def peer() -> Iterator[Callable[[FleetConfig], zenoh.Session]]:
    """`peer(cfg)`: a peer session connected to the fleet's registry, closed at teardown."""
    sessions: list[zenoh.Session] = []

    def make(cfg: FleetConfig) -> zenoh.Session:
        session = open_session(
            mode="peer",
            connect=[cfg.registry.endpoint],
            listen=["tcp/127.0.0.1:0"],
            lease_ms=LEASE_MS,
        )
        sessions.append(session)
        return session

    try:
        yield make
    finally:
        for session in reversed(sessions):
            if not session.is_closed():
                session.close()


# -- the fakes -------------------------------------------------------------------------------------
class FakeDeployment:
    """A cloud daemon's registry-facing half: token, probe and ctl with its epoch rules (a
    request with an epoch lower than the one held for the robot is refused; the same epoch is
    idempotent), and the robot's service key declared (complete) in service only."""

    def __init__(
        self,
        session: zenoh.Session,
        cfg: FleetConfig,
        name: str,
        *,
        digest: str,
        protocol_version: int = PROTOCOL_VERSION,
        capabilities: tuple[str, ...] = CAPABILITIES,
        serving: tuple[str, ...] = (),
        ctl_answer: bytes | None = None,
    ) -> None:
        """`serving`: robots it serves from the start; `ctl_answer`: raw bytes to answer every
        ctl request with instead of the protocol (a broken deployment)."""
        self.session = session
        self.ctl_answer = ctl_answer
        self.fleet = cfg.fleet
        self.service = cfg.service
        self.name = name
        self.digest = digest
        self.protocol_version = protocol_version
        self.capabilities = capabilities
        self.cond = threading.Condition()
        self.ctl_log: list[CtlRequest] = []
        self.probes = 0
        self.epochs: dict[str, int] = {}
        self.states: dict[str, DeploymentState] = {}
        self.served: dict[str, int] = {}
        self._service_keys: dict[str, Any] = {}
        for robot in serving:  # e.g. a process that missed its standby
            self._serve(robot, 0)
        self._declared = [
            session.declare_queryable(keys.dep_probe(self.fleet, name), self._on_probe),
            session.declare_queryable(keys.dep_ctl(self.fleet, name), self._on_ctl),
        ]
        self.token = session.liveliness().declare_token(keys.alive_cloud(self.fleet, name))

    def _on_probe(self, query: zenoh.Query) -> None:
        with query:
            ProbeRequest.from_wire(query.payload.to_bytes() if query.payload else b"")
            with self.cond:
                self.probes += 1
                reply = ProbeReply(
                    deployment=self.name,
                    protocol_version=self.protocol_version,
                    capabilities=self.capabilities,
                    service=self.service,
                    model_digest=self.digest,
                    states=dict(self.states),
                    load=0,
                    capacity=4,
                )
            query.reply(keys.dep_probe(self.fleet, self.name), reply.to_wire())

    def _on_ctl(self, query: zenoh.Query) -> None:
        with query:
            if self.ctl_answer is not None:
                query.reply(keys.dep_ctl(self.fleet, self.name), self.ctl_answer)
                return
            req = CtlRequest.from_wire(query.payload.to_bytes() if query.payload else b"")
            assert req.robot is not None
            with self.cond:
                known = self.epochs.get(req.robot, 0)
                if req.epoch < known:
                    reply = self._reply(req, self.states.get(req.robot), known, ok=False)
                elif req.op is CtlOp.SERVICE:
                    self._serve(req.robot, req.epoch)
                    reply = self._reply(req, DeploymentState.SERVICE, req.epoch)
                else:
                    self._standby(req.robot, req.epoch)
                    reply = self._reply(req, DeploymentState.STANDBY, req.epoch)
                self.ctl_log.append(req)
                self.cond.notify_all()
            query.reply(keys.dep_ctl(self.fleet, self.name), reply.to_wire())

    def _reply(
        self, req: CtlRequest, state: DeploymentState | None, epoch: int, ok: bool = True
    ) -> CtlReply:
        reason = "" if ok else f"stale epoch {req.epoch}: holding {epoch}"
        return CtlReply(
            ok=ok,
            deployment=self.name,
            op=req.op,
            robot=req.robot,
            epoch=epoch,
            state=state,
            reason=reason,
        )

    def _serve(self, robot: str, epoch: int) -> None:
        # Declared before the ack: the registry publishes the route only after it.
        if robot not in self._service_keys:
            key = keys.svc_infer(self.fleet, self.service, robot)

            def infer(query: zenoh.Query) -> None:
                with query:
                    with self.cond:
                        self.served[robot] = self.served.get(robot, 0) + 1
                    query.reply(key, self.name.encode())

            self._service_keys[robot] = self.session.declare_queryable(key, infer, complete=True)
        self.epochs[robot] = epoch
        self.states[robot] = DeploymentState.SERVICE

    def _standby(self, robot: str, epoch: int) -> None:
        declared = self._service_keys.pop(robot, None)
        if declared is not None:
            declared.undeclare()
        self.epochs[robot] = epoch
        self.states[robot] = DeploymentState.STANDBY

    def wait_ctl(
        self, what: str, predicate: Callable[[CtlRequest], bool], timeout_s: float = WAIT_S
    ) -> CtlRequest:
        """The first ctl request received (so far or from now on) that matches `predicate`."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                for req in self.ctl_log:
                    if predicate(req):
                        return req
                left = deadline - time.monotonic()
                if left <= 0:
                    pytest.fail(f"{self.name}: no {what} within {timeout_s} s: {self.ctl_log}")
                self.cond.wait(left)

    def die(self) -> None:
        """Vanish like a killed process: the session closes, the token goes with it."""
        self.session.close()


class FakeRobot:
    """A robot daemon's registry-facing half: token, route subscriber, telemetry, probe reports."""

    def __init__(self, session: zenoh.Session, cfg: FleetConfig, name: str = ROBOT) -> None:
        self.session = session
        self.fleet = cfg.fleet
        self.service = cfg.service
        self.name = name
        self.cond = threading.Condition()
        self.routes: list[RouteChange] = []
        self.frame = 0
        self._sub = session.declare_subscriber(keys.route(self.fleet, name), self._on_route)
        self.token = session.liveliness().declare_token(keys.alive_robot(self.fleet, name))

    def _on_route(self, sample: zenoh.Sample) -> None:
        change = RouteChange.from_wire(sample.payload.to_bytes())
        with self.cond:
            self.routes.append(change)
            self.cond.notify_all()

    def wait_route(
        self, what: str, predicate: Callable[[RouteChange], bool], timeout_s: float = WAIT_S
    ) -> RouteChange:
        """The first route change published (so far or from now on) matching `predicate`."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                for change in self.routes:
                    if predicate(change):
                        return change
                left = deadline - time.monotonic()
                if left <= 0:
                    pytest.fail(f"{self.name}: no route {what} within {timeout_s} s: {self.routes}")
                self.cond.wait(left)

    def frame_done(
        self,
        deployment: str | None,
        remote_s: float,
        *,
        fallback: bool = False,
        reason: str | None = None,
    ) -> None:
        """Publish one frame's telemetry: `remote_s` split into transfer and cloud time."""
        record = self.record(deployment, remote_s, fallback=fallback, reason=reason)
        self.session.put(keys.tele(self.fleet, self.name), record.to_wire())

    def record(
        self,
        deployment: str | None,
        remote_s: float,
        *,
        fallback: bool = False,
        reason: str | None = None,
        robot: str | None = None,
    ) -> TelemetryRecord:
        """The next frame's record (of `robot`, default this one)."""
        record = TelemetryRecord(
            robot=robot or self.name,
            frame=self.frame,
            action="cut:1",
            bytes_up=1000,
            bytes_down=100,
            prefix_s=0.001,
            transfer_s=remote_s / 2,
            cloud_s=remote_s / 2,
            suffix_local_s=0.002 if fallback else 0.0,
            latency_s=remote_s + 0.001,
            robot_cpu_s=0.001,
            energy_j=0.01,
            deployment=deployment,
            fallback=fallback,
            reason=reason,
            at=time.time(),
        )
        self.frame += 1
        return record

    def probed(self, deployment: str, rtt_s: float) -> None:
        """Publish one probe report of `deployment`."""
        report = ProbeReport(
            robot=self.name,
            deployment=deployment,
            ok=True,
            at=time.time(),
            rtt_s=rtt_s,
            load=0,
            capacity=4,
        )
        self.session.put(keys.tele_probe(self.fleet, self.name), report.to_wire())

    def infer(self) -> list[str]:
        """Who answers the robot's service key (anycast: exactly one)."""
        replies = self.session.get(
            keys.svc_infer(self.fleet, self.service, self.name),
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=QUERY_TIMEOUT_S,
        )
        return [r.ok.payload.to_string() for r in replies if r.ok is not None]


def ask(session: zenoh.Session, key: str, payload: bytes | None) -> Any:
    """The decoded single reply to a get on `key` (fails the test when none comes)."""
    replies = session.get(key, payload=payload, timeout=QUERY_TIMEOUT_S)
    messages = [decode(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    assert len(messages) == 1, f"{key}: {len(messages)} replies"
    return messages[0]


def view(session: zenoh.Session, cfg: FleetConfig, name: str, **filters: Any) -> Any:
    """The rows of one RIB view."""
    payload = RibQuery(**filters).to_wire() if filters else None
    return ask(session, keys.rib(cfg.fleet, name), payload).rows


def wait_view(
    session: zenoh.Session,
    cfg: FleetConfig,
    name: str,
    predicate: Callable[[tuple[Any, ...]], bool],
    what: str,
    timeout_s: float = WAIT_S,
) -> tuple[Any, ...]:
    """Query view `name` until its rows satisfy `predicate` (each round waits on a reply)."""
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while True:
        rows = view(session, cfg, name)
        if predicate(rows):
            return rows
        if time.monotonic() > deadline:
            pytest.fail(f"the registry's {name} never showed {what} within {timeout_s} s: {rows}")
        pause.wait(0.05)


def pace(stop: threading.Event, count: int, step: Callable[[int], None]) -> None:
    """Run `step` for `count` frames at the fake robot's frame rate (stops early on `stop`)."""
    for i in range(count):
        step(i)
        if stop.wait(FRAME_PERIOD_S):
            return


class Fleet:
    """A started registry with edge-1 and edge-2 registered and robot-1 routed to edge-1."""

    def __init__(
        self,
        cfg: FleetConfig,
        registry: RunningRegistry,
        edges: dict[str, FakeDeployment],
        robot: FakeRobot,
        observer: zenoh.Session,
    ) -> None:
        self.cfg = cfg
        self.registry = registry
        self.edges = edges
        self.robot = robot
        self.observer = observer


@pytest.fixture
def routed(
    fleet: tuple[Path, FleetConfig],
    start_registry: Callable[..., RunningRegistry],
    peer: Callable[[FleetConfig], zenoh.Session],
) -> Fleet:
    """Registry, edge-1, edge-2, robot-1 routed to edge-1 (epoch 1)."""
    _, cfg = fleet
    registry = start_registry(cfg)
    digest = model_digest(cfg)
    edges = {
        name: FakeDeployment(peer(cfg), cfg, name, digest=digest) for name in ("edge-1", "edge-2")
    }
    robot = FakeRobot(peer(cfg), cfg)
    first = robot.wait_route("to edge-1", lambda c: c.deployment is not None)
    assert (first.deployment, first.epoch) == ("edge-1", 1)
    return Fleet(cfg, registry, edges, robot, peer(cfg))


# -- tests -----------------------------------------------------------------------------------------
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
