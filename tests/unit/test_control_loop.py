"""The registry's control loop (`registry.control_loop.ControlLoop`) driven without Zenoh
(STYLE 19): membership changes, probe outcomes and scheduling rounds are handed to it as the
daemon's queue and tick would, over a fake network (deployments that answer ctl with the cloud
daemon's epoch rules, route changes kept) and a fake probe pool. The RIB (in memory), the
registrar, the switch protocol, the scheduler and the measurements are the real ones, the last
three on a fake clock, so hysteresis is waited out by moving the clock, not by sleeping.

What must hold: a robot whose deployment's token goes is moved at once to a live one (or told
to compute locally when none is left), the dead deployment is never sent a ctl request, and the
next round leaves the route alone; a latency bound violated for less than the hysteresis moves
nothing, and once it has held that long the round moves the robot to the deployment its probes
say meets the bound. Every move is a published route change, a RIB route event with its reason,
and the old deployment in standby.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common import keys
from common.config import fleet_from_dict
from common.keys import Role
from common.membership import MemberChange
from common.models import file_digest
from common.throttled_log import ThrottledLog
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
    RouteChange,
)
from common.wire.telemetry import ProbeReport, TelemetryRecord
from registry.control_loop import ControlLoop
from registry.latency import LatencyBound
from registry.measurements import Measurements
from registry.prober import Probed
from registry.registration import Registrar, fleet_model_digest
from registry.rib import Rib
from registry.rib_events import EventKind
from registry.rib_store import MEMORY
from registry.scheduler import Reason, Scheduler, SchedulerParams
from registry.switch import Switcher

FLEET = "unit"
SERVICE = "vision"
ROBOT = "robot-1"
OLD, NEW = "edge-1", "edge-2"  # in service for the robot at first, and in standby
BOUND_S = 0.1
WINDOW = 5
HYSTERESIS_S = 1.0
DEADLINE_S = 0.5
CAPACITY = 8
# What the robot sees through the slow deployment, and what its probes say of the other one.
SLOW_S = 0.3
FAST_S = 0.02
WALL_EPOCH_S = 1.7e9


@pytest.fixture(autouse=True)
def no_zenoh_session(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests run without a network: opening a Zenoh session fails the test."""

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a unit test of the control loop opened a Zenoh session")

    monkeypatch.setattr(zenoh, "open", refuse)


class FakeClock:
    """The scheduler's and the measurements' monotonic clock, and the RIB's wall clock."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return WALL_EPOCH_S + self.t


@dataclass
class FakeDeployment:
    """A cloud daemon as the registry sees it: ctl with its epoch rules (a service request
    needs a newer epoch than the one held for the robot, a standby one at least as new), and
    its probe reply. A dead one answers nothing."""

    name: str
    digest: str
    alive: bool = True
    epochs: dict[str, int] = field(default_factory=dict)
    states: dict[str, DeploymentState] = field(default_factory=dict)

    def handle(self, req: CtlRequest) -> CtlReply:
        assert req.robot is not None
        known = self.epochs.get(req.robot, 0)
        fresh = req.epoch > known if req.op is CtlOp.SERVICE else req.epoch >= known
        if not fresh:
            state = self.states.get(req.robot)
            return CtlReply(
                ok=False,
                deployment=self.name,
                op=req.op,
                robot=req.robot,
                epoch=known,
                state=state,
                reason="stale epoch",
            )
        state = DeploymentState.SERVICE if req.op is CtlOp.SERVICE else DeploymentState.STANDBY
        self.epochs[req.robot], self.states[req.robot] = req.epoch, state
        return CtlReply(
            ok=True, deployment=self.name, op=req.op, robot=req.robot, epoch=req.epoch, state=state
        )

    def probe_reply(self) -> ProbeReply:
        return ProbeReply(
            deployment=self.name,
            protocol_version=PROTOCOL_VERSION,
            capabilities=(CAP_INFER, CAP_PROBE, CAP_CTL),
            service=SERVICE,
            model_digest=self.digest,
            states=dict(self.states),
            load=0,
            capacity=CAPACITY,
            epochs=dict(self.epochs),
        )


class FakeNetwork:
    """The registry's transport (`registry.switch.SwitchTransport`) without Zenoh: ctl requests
    answered by the fake deployments at once (a dead one never answers) and kept, in order, as
    (op, deployment, epoch); route changes kept as published."""

    def __init__(self, deployments: list[FakeDeployment]) -> None:
        self.deployments = {d.name: d for d in deployments}
        self.ctl: list[tuple[str, str, int]] = []
        self.published: list[RouteChange] = []

    def send_ctl(self, deployment: str, request: CtlRequest, timeout_s: float) -> CtlReply | None:
        self.ctl.append((request.op.value, deployment, request.epoch))
        dep = self.deployments[deployment]
        return dep.handle(request) if dep.alive else None

    def publish_route(self, change: RouteChange) -> None:
        self.published.append(change)


class FakeProber:
    """The probe pool without Zenoh: keeps what the loop asks to probe; the test hands the
    outcome back to the loop, as the daemon's queue would."""

    def __init__(self) -> None:
        self.submitted: list[tuple[str, bool]] = []

    def submit(self, deployment: str, *, refresh: bool) -> None:
        self.submitted.append((deployment, refresh))


@dataclass
class Fleet:
    """A control loop over the fakes, and what the test looks at."""

    loop: ControlLoop
    rib: Rib
    clock: FakeClock
    network: FakeNetwork
    prober: FakeProber
    measurements: Measurements
    frame: int = 0

    def member(self, role: Role, member: str, *, alive: bool) -> None:
        """A liveliness token came or went (the daemon's membership callback)."""
        change = MemberChange(
            role=role.value, id=member, alive=alive, seed=False, alive_ids=frozenset()
        )
        self.loop.handle(change)

    def kill(self, deployment: str) -> None:
        """`deployment`'s process dies: it answers nothing, then its token goes."""
        self.network.deployments[deployment].alive = False
        self.member(Role.CLOUD, deployment, alive=False)

    def answer_probes(self) -> None:
        """Hand every probe asked for its outcome (the deployments answer at once)."""
        submitted, self.prober.submitted = self.prober.submitted, []
        for deployment, refresh in submitted:
            reply = self.network.deployments[deployment].probe_reply()
            self.loop.handle(Probed(deployment, reply, "", refresh))

    def telemetry(self, deployment: str, remote_s: float, frames: int = WINDOW) -> None:
        """`frames` frames answered by `deployment`, `remote_s` each past the robot."""
        for _ in range(frames):
            record = TelemetryRecord(
                robot=ROBOT,
                frame=self.frame,
                action="cut:1",
                bytes_up=1000,
                bytes_down=100,
                prefix_s=0.001,
                transfer_s=remote_s / 2,
                cloud_s=remote_s / 2,
                suffix_local_s=0.0,
                latency_s=remote_s,
                robot_cpu_s=0.001,
                energy_j=0.0,
                deployment=deployment,
                fallback=False,
                reason=None,
            )
            self.frame += 1
            self.measurements.record_telemetry(record, keys.tele(FLEET, ROBOT))

    def probes(self, deployment: str, latency_s: float, count: int) -> None:
        """`count` probe reports of the robot's: `deployment` would serve it in `latency_s`."""
        for _ in range(count):
            report = ProbeReport(
                robot=ROBOT,
                deployment=deployment,
                ok=True,
                at=self.clock.wall(),
                rtt_s=latency_s,
                expected_latency_s=latency_s,
                load=0,
                capacity=CAPACITY,
            )
            self.measurements.record_probe_report(report, keys.tele_probe(FLEET, ROBOT))

    def routes(self) -> list[tuple[str, str | None, int, str]]:
        """Every route change published so far: (robot, deployment, epoch, reason)."""
        return [(c.robot, c.deployment, c.epoch, c.reason) for c in self.network.published]

    def events(self, after: int) -> list[tuple[str, str | None, int | None, str]]:
        """The RIB's events newer than sequence number `after`: (kind, deployment, epoch,
        reason)."""
        return [
            (e.kind, e.deployment, e.epoch, e.reason) for e in self.rib.events() if e.seq > after
        ]

    def last_event(self) -> int:
        events = self.rib.events(limit=1)
        return events[-1].seq if events else 0


def _bad_sample(where: str, problem: str) -> None:
    raise AssertionError(f"the test fed a bad sample ({where}): {problem}")


@pytest.fixture
def fleet(tmp_path: Path) -> Iterator[Fleet]:
    """edge-1 and edge-2 registered, robot-1 up and placed on edge-1 (initial_policy) at
    epoch 1 by a first round."""
    model = tmp_path / "model.onnx"
    model.write_bytes(b"the registry only reads this file's digest")
    cfg = fleet_from_dict(
        {
            "fleet": FLEET,
            "service": SERVICE,
            "model": str(model),
            "machines": {OLD: {"role": "cloud"}, NEW: {"role": "cloud"}, ROBOT: {"role": "robot"}},
            "initial_policy": {ROBOT: "robot", OLD: "service", NEW: "standby"},
            "latency_bound": {
                "stat": "median",
                "seconds": BOUND_S,
                "window": WINDOW,
                "hysteresis_s": HYSTERESIS_S,
            },
            "deadline_s": DEADLINE_S,
        }
    )
    clock = FakeClock()
    params = SchedulerParams()
    bound = LatencyBound(
        stat=cfg.latency_bound.stat,
        seconds=cfg.latency_bound.seconds,
        window=cfg.latency_bound.window,
        hysteresis_s=cfg.latency_bound.hysteresis_s,
        better_margin=cfg.latency_bound.better_margin,
    )
    rib = Rib(MEMORY, clock=clock.wall)
    digest = file_digest(model)
    network = FakeNetwork([FakeDeployment(OLD, digest), FakeDeployment(NEW, digest)])
    prober = FakeProber()
    measurements = Measurements(
        bound.window,
        deadline_s=cfg.deadline_s,
        timeout_count=params.timeout_count,
        on_bad_sample=_bad_sample,
        clock=clock.now,
        wall_clock=clock.wall,
    )
    loop = ControlLoop(
        cfg,
        rib=rib,
        transport=network,  # type: ignore[arg-type]
        switcher=Switcher(rib, network, sender="registry", clock=clock.wall),
        registrar=Registrar(FLEET, rib, SERVICE, fleet_model_digest(cfg)),
        prober=prober,  # type: ignore[arg-type]
        pools=None,  # an anycast fleet
        scheduler=Scheduler(bound, params, clock=clock.now),
        measurements=measurements,
        throttled=ThrottledLog(logging.getLogger("registry.daemon")),
        started_at=0.0,
        restore_grace_s=0.0,
    )
    fleet = Fleet(loop, rib, clock, network, prober, measurements)
    fleet.member(Role.CLOUD, OLD, alive=True)
    fleet.member(Role.CLOUD, NEW, alive=True)
    assert prober.submitted == [(OLD, False), (NEW, False)]  # registration probes
    fleet.answer_probes()
    fleet.member(Role.ROBOT, ROBOT, alive=True)
    loop.schedule_all()
    assert fleet.routes() == [(ROBOT, OLD, 1, Reason.INITIAL.value)]
    assert network.ctl == [("service", OLD, 1)]
    try:
        yield fleet
    finally:
        rib.close()


# -- a dead deployment -----------------------------------------------------------------------------
def test_a_robot_whose_deployment_dies_is_moved_at_once_and_the_round_leaves_it(
    fleet: Fleet,
) -> None:
    seq = fleet.last_event()
    fleet.network.ctl.clear()

    fleet.kill(OLD)

    assert fleet.routes()[1:] == [(ROBOT, NEW, 2, Reason.DEPLOYMENT_LOST.value)]
    # The dead deployment is sent nothing: its standby is only recorded.
    assert fleet.network.ctl == [("service", NEW, 2)]
    assert fleet.events(seq) == [
        (EventKind.DEPLOYMENT_DOWN.value, OLD, None, "liveliness token gone"),
        (EventKind.ROUTE.value, NEW, 2, f"{Reason.DEPLOYMENT_LOST.value}: {OLD} -> {NEW}"),
        (EventKind.STATE.value, OLD, 2, DeploymentState.STANDBY.value),
    ]
    route = fleet.rib.route(ROBOT)
    assert route is not None and (route.deployment, route.epoch) == (NEW, 2)
    assert fleet.measurements.route(ROBOT)[:2] == (NEW, 2)
    dead = fleet.rib.deployment(OLD)
    assert dead is not None and not dead.alive

    # The next round finds the robot served by a live deployment: nothing moves.
    fleet.clock.t += HYSTERESIS_S
    seq = fleet.last_event()
    fleet.loop.schedule_all()
    assert fleet.routes()[1:] == [(ROBOT, NEW, 2, Reason.DEPLOYMENT_LOST.value)]
    assert fleet.events(seq) == []


def test_a_robot_left_without_a_live_deployment_is_told_to_compute_locally(
    fleet: Fleet,
) -> None:
    fleet.kill(NEW)  # in standby for the robot: nothing to move
    assert fleet.routes()[1:] == []

    fleet.network.ctl.clear()
    fleet.kill(OLD)

    assert fleet.routes()[1:] == [(ROBOT, None, 2, Reason.DEPLOYMENT_LOST.value)]
    assert fleet.network.ctl == []  # nobody alive to ask
    route = fleet.rib.route(ROBOT)
    assert route is not None and (route.deployment, route.epoch) == (None, 2)
    fleet.loop.schedule_all()
    assert len(fleet.routes()) == 2  # a round with nothing alive changes nothing


# -- a latency violation ---------------------------------------------------------------------------
def test_a_latency_violation_moves_the_robot_once_it_has_held_for_the_hysteresis(
    fleet: Fleet,
) -> None:
    """The robot's frames through edge-1 take SLOW_S (median bound BOUND_S); its probes say
    edge-2 would take FAST_S. The first round that sees the violation starts the hysteresis and
    moves nothing; a round just short of it moves nothing either; the round after it moves the
    robot to edge-2, which is put in service before edge-1 is put in standby."""
    params = fleet.loop.scheduler.params
    fleet.probes(NEW, FAST_S, params.min_probe_samples)
    fleet.telemetry(OLD, SLOW_S)
    fleet.network.ctl.clear()
    seq = fleet.last_event()

    fleet.loop.schedule_all()
    fleet.clock.t += HYSTERESIS_S / 2
    fleet.loop.schedule_all()
    assert fleet.routes()[1:] == []
    assert fleet.network.ctl == []
    assert fleet.events(seq) == []

    fleet.clock.t += HYSTERESIS_S / 2
    fleet.loop.schedule_all()

    assert fleet.routes()[1:] == [(ROBOT, NEW, 2, Reason.BOUND_VIOLATION.value)]
    assert fleet.network.ctl == [("service", NEW, 2), ("standby", OLD, 2)]
    assert fleet.events(seq) == [
        (EventKind.ROUTE.value, NEW, 2, f"{Reason.BOUND_VIOLATION.value}: {OLD} -> {NEW}"),
        (EventKind.STATE.value, OLD, 2, DeploymentState.STANDBY.value),
    ]
    assert fleet.network.deployments[OLD].states[ROBOT] is DeploymentState.STANDBY
    assert fleet.network.deployments[NEW].states[ROBOT] is DeploymentState.SERVICE
    assert fleet.measurements.route(ROBOT)[:2] == (NEW, 2)


def test_a_violation_with_no_better_deployment_moves_nothing(fleet: Fleet) -> None:
    """The bound is violated past the hysteresis, but the robot's probes say edge-2 is no
    faster: moving would trade one violation for another, so the route stays."""
    params = fleet.loop.scheduler.params
    fleet.probes(NEW, SLOW_S, params.min_probe_samples)
    fleet.telemetry(OLD, SLOW_S)
    seq = fleet.last_event()

    fleet.loop.schedule_all()
    fleet.clock.t += HYSTERESIS_S
    fleet.loop.schedule_all()

    assert fleet.routes()[1:] == []
    assert fleet.events(seq) == []
