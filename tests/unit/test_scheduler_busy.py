"""`busy` replies as a scheduling signal: robots refused for want of room move to a deployment
with room, paced and with margin, until every deployment serves, and then stay."""

from __future__ import annotations

from collections import Counter

import pytest

from common.wire.telemetry import FallbackReason, TelemetryRecord
from registry.latency import LatencyBound, Stat, WindowStats
from registry.measurements import Measurements
from registry.scheduler import (
    DeploymentView,
    Reason,
    RobotView,
    Scheduler,
    SchedulerParams,
)

SERVICE = "detect"
BOUND = LatencyBound(stat=Stat.MEDIAN, seconds=0.1, hysteresis_s=1.0, better_margin=0.2)
WINDOW = 20  # frames in a robot's busy window


class FakeClock:
    """Monotonic clock under the test's control."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Fleet:
    """Synthetic deployments that each serve `serves` robots at once: past that, every robot
    routed there sees the excess share of its frames refused `busy`, and the deployment's load
    is its capacity (full)."""

    def __init__(self, routes: dict[str, str], serves: dict[str, int], clock: FakeClock) -> None:
        self.routes = routes
        self.serves = serves
        self.clock = clock

    def counts(self) -> Counter[str]:
        return Counter(self.routes.values())

    def deployments(self) -> list[DeploymentView]:
        n = self.counts()
        return [
            DeploymentView(id=d, service=SERVICE, load=min(n[d], cap), capacity=cap)
            for d, cap in self.serves.items()
        ]

    def view(self, robot: str) -> RobotView:
        route = self.routes[robot]
        n, cap = self.counts()[route], self.serves[route]
        busy = round(WINDOW * max(0, n - cap) / n)
        tele = WindowStats.of([0.04] * 20, last_at=self.clock.now)
        return RobotView(
            id=robot, service=SERVICE, route=route, telemetry=tele, busy=busy, offloaded=WINDOW
        )

    def profiles(self) -> dict[str, WindowStats]:
        return {d: WindowStats.of([0.04] * 10, last_at=self.clock.now) for d in self.serves}


def run_rounds(sched: Scheduler, fleet: Fleet, seconds: float, step_s: float = 0.5) -> list[str]:
    """Scheduling rounds every `step_s`, moves carried out at once; the moves' reasons."""
    reasons: list[str] = []
    end = fleet.clock.now + seconds
    while fleet.clock.now < end:
        deployments = fleet.deployments()  # one load snapshot per round, as the daemon reads
        for robot in sorted(fleet.routes):
            d = sched.evaluate(fleet.view(robot), deployments, fleet.profiles())
            if d is not None and d.to_deployment is not None:
                sched.record_switch(robot, d.from_deployment, d.to_deployment, d.reason)
                fleet.routes[robot] = d.to_deployment
                reasons.append(d.reason.value)
        fleet.clock.now += step_s
    return reasons


def test_robots_refused_busy_move_until_both_deployments_serve_then_stay() -> None:
    clock = FakeClock()
    sched = Scheduler(BOUND, SchedulerParams(), clock=clock)
    fleet = Fleet({f"r{i}": "edge-1" for i in range(8)}, {"edge-1": 4, "edge-2": 4}, clock)

    reasons = run_rounds(sched, fleet, 30.0)

    assert fleet.counts() == Counter({"edge-1": 4, "edge-2": 4})
    assert set(reasons) == {Reason.BUSY.value}
    assert len(reasons) == 4  # each move went one way: nobody came back
    assert run_rounds(sched, fleet, 120.0) == []  # and they stay, past the flap window


def test_busy_moves_are_paced_per_target() -> None:
    # One load snapshot per round: without the arrival gap every busy robot of the round would
    # move to the same deployment before its load shows any of them.
    clock = FakeClock()
    sched = Scheduler(BOUND, SchedulerParams(busy_arrival_gap_s=2.0), clock=clock)
    fleet = Fleet({f"r{i}": "edge-1" for i in range(8)}, {"edge-1": 4, "edge-2": 4}, clock)
    run_rounds(sched, fleet, 1.0)  # the hysteresis: nothing yet
    assert fleet.counts()["edge-2"] == 0
    run_rounds(sched, fleet, 0.5)
    assert fleet.counts()["edge-2"] == 1


def test_no_move_when_no_deployment_has_room() -> None:
    clock = FakeClock()
    sched = Scheduler(BOUND, SchedulerParams(), clock=clock)
    fleet = Fleet(
        {**{f"a{i}": "edge-1" for i in range(6)}, **{f"b{i}": "edge-2" for i in range(6)}},
        {"edge-1": 4, "edge-2": 4},
        clock,
    )
    assert run_rounds(sched, fleet, 20.0) == []


def test_a_few_busy_frames_do_not_move_a_robot() -> None:
    clock = FakeClock()
    sched = Scheduler(BOUND, SchedulerParams(busy_share=0.1), clock=clock)
    deps = [
        DeploymentView(id="edge-1", service=SERVICE, load=3, capacity=6),
        DeploymentView(id="edge-2", service=SERVICE, load=3, capacity=6),
    ]
    profiles = {d.id: WindowStats.of([0.04] * 10, last_at=clock.now) for d in deps}
    tele = WindowStats.of([0.04] * 20, last_at=clock.now)
    for busy, offloaded in ((2, 20), (5, 8)):  # at the share; too few frames to judge
        view = RobotView("r", SERVICE, "edge-1", tele, busy=busy, offloaded=offloaded)
        for _ in range(10):
            assert sched.evaluate(view, deps, profiles) is None
            clock.now += 0.5


def test_room_needs_headroom() -> None:
    assert DeploymentView("d", SERVICE, load=3, capacity=4).has_room(0.25)
    assert not DeploymentView("d", SERVICE, load=4, capacity=5).has_room(0.25)
    assert DeploymentView("d", SERVICE).has_room(0.25)  # capacity unknown: nothing says full


@pytest.mark.parametrize(
    "kw", [{"busy_share": 1.0}, {"busy_headroom": -0.1}, {"busy_min_frames": 0}]
)
def test_params_checked(kw: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="scheduler busy_"):
        SchedulerParams(**kw)  # type: ignore[arg-type]


def _record(robot: str, deployment: str | None, reason: FallbackReason | None) -> TelemetryRecord:
    return TelemetryRecord(
        robot=robot,
        frame=0,
        action="cut:0",
        bytes_up=1,
        bytes_down=1,
        prefix_s=0.0,
        transfer_s=0.01,
        cloud_s=0.02,
        suffix_local_s=0.0,
        latency_s=0.03,
        robot_cpu_s=0.0,
        energy_j=0.0,
        deployment=deployment,
        fallback=reason is not None,
        reason=reason,
    )


def _measurements() -> Measurements:
    return Measurements(
        20, deadline_s=0.5, timeout_count=3, on_bad_sample=lambda w, p: None, busy_window=10
    )


def test_measurements_count_busy_frames_per_robot_and_route() -> None:
    m = _measurements()
    m.set_route("r1", "edge-1", 1)
    m.set_route("r2", "edge-1", 1)
    for i in range(12):
        busy = i % 3 == 0
        rec = _record("r1", "edge-1", FallbackReason.BUSY if busy else None)
        m.record_telemetry(rec, "k")
    m.record_telemetry(_record("r1", None, FallbackReason.TIMEOUT), "k")
    m.record_telemetry(_record("r1", "edge-2", FallbackReason.BUSY), "k")
    m.record_telemetry(_record("r2", "edge-1", None), "k")

    r1 = m.for_scheduler("r1", "edge-1")
    assert (r1.busy, r1.offloaded) == (3, 10)  # the last 10 frames to edge-1: i = 2..11
    r2 = m.for_scheduler("r2", "edge-1")
    assert (r2.busy, r2.offloaded) == (0, 1)

    m.set_route("r1", "edge-2", 2)  # a new route starts a new count
    r1 = m.for_scheduler("r1", "edge-2")
    assert (r1.busy, r1.offloaded) == (0, 0)
