"""The registry's test fleet over real Zenoh on loopback: the fleet file, the registry daemon run
in-process (`RunningRegistry`), and deployments and a robot played with real peer sessions
speaking common/wire (`FakeDeployment` answers probe and ctl with the cloud daemon's epoch rules
and declares the service key; `FakeRobot` holds a token, publishes telemetry and probe reports,
and follows its route key), with the fixtures that start them."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

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
    ProbeReply,
    ProbeRequest,
    RibQuery,
    RouteChange,
)
from common.wire.telemetry import ProbeReport, TelemetryRecord
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
T = TypeVar("T")


def wait_logged(
    cond: threading.Condition,
    log: list[T],
    predicate: Callable[[T], bool],
    failure: str,
    timeout_s: float = WAIT_S,
) -> T:
    """The first entry of `log` (appended to under `cond`, which is notified) that matches
    `predicate`, so far or from now on; the test fails with `failure` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    with cond:
        while True:
            for entry in log:
                if predicate(entry):
                    return entry
            left = deadline - time.monotonic()
            if left <= 0:
                pytest.fail(f"{failure} within {timeout_s} s: {log}")
            cond.wait(left)


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
        self.token = session.liveliness().declare_token(keys.alive_deployment(self.fleet, name))

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
        return wait_logged(self.cond, self.ctl_log, predicate, f"{self.name}: no {what}", timeout_s)

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
