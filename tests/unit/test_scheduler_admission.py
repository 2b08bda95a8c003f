"""Admission: when every deployment is full a robot to be placed gets no route (`no_capacity`),
is told once, and is placed by a later round as soon as a deployment has room."""

from __future__ import annotations

import pytest

from common.wire.registry import NO_CAPACITY_REASON
from registry.latency import LatencyBound, Stat, WindowStats
from registry.scheduler import (
    DeploymentView,
    Reason,
    RobotView,
    RouteDecision,
    Scheduler,
    SchedulerParams,
)

ROBOT = "robot-1"
SERVICE = "detect"
BOUND = LatencyBound(stat=Stat.MEDIAN, seconds=0.1, hysteresis_s=1.0, better_margin=0.2)
NOW_S = 1000.0


@pytest.fixture
def sched() -> Scheduler:
    return Scheduler(BOUND, SchedulerParams(), clock=lambda: NOW_S)


def dep(name: str, load: int, capacity: int, **kw: bool) -> DeploymentView:
    return DeploymentView(id=name, service=SERVICE, load=load, capacity=capacity, **kw)


def robot(route: str | None) -> RobotView:
    return RobotView(id=ROBOT, service=SERVICE, route=route)


def fast() -> dict[str, WindowStats]:
    return {d: WindowStats.of([0.02] * 10, last_at=NOW_S) for d in ("a", "b")}


def test_the_reason_is_the_wire_string() -> None:
    assert Reason.NO_CAPACITY.value == NO_CAPACITY_REASON == "no_capacity"


def test_every_deployment_full_leaves_a_new_robot_local_with_the_reason(
    sched: Scheduler,
) -> None:
    full = [dep("a", load=4, capacity=4), dep("b", load=5, capacity=4)]
    decision = sched.evaluate(robot(None), full, fast())
    assert decision == RouteDecision(ROBOT, None, None, Reason.NO_CAPACITY)


def test_the_robot_is_told_once_then_placed_when_a_deployment_has_room(
    sched: Scheduler,
) -> None:
    full = [dep("a", load=4, capacity=4), dep("b", load=4, capacity=4)]
    sched.record_switch(ROBOT, None, None, Reason.NO_CAPACITY)
    # Regression: without the memory every round would publish the same refusal again.
    assert sched.evaluate(robot(None), full, fast()) is None
    room = [dep("a", load=4, capacity=4), dep("b", load=3, capacity=4)]
    decision = sched.evaluate(robot(None), room, fast())
    assert decision is not None
    assert (decision.to_deployment, decision.reason) == ("b", Reason.INITIAL)


def test_a_robot_placed_then_refused_again_is_told_again(sched: Scheduler) -> None:
    full = [dep("a", load=4, capacity=4), dep("b", load=4, capacity=4)]
    sched.record_switch(ROBOT, None, None, Reason.NO_CAPACITY)
    # Placed meanwhile (a placement is not recorded): the next refusal is news to the robot.
    assert sched.evaluate(robot("a"), full, fast()) is None
    decision = sched.evaluate(robot(None), full, fast())
    assert decision is not None and decision.reason is Reason.NO_CAPACITY


def test_a_lost_deployment_with_every_other_full_drops_the_route_for_capacity(
    sched: Scheduler,
) -> None:
    deps = [dep("a", load=0, capacity=4, alive=False), dep("b", load=4, capacity=4)]
    decision = sched.evaluate(robot("a"), deps, fast())
    assert decision == RouteDecision(ROBOT, "a", None, Reason.NO_CAPACITY)


def test_unknown_capacity_is_never_full(sched: Scheduler) -> None:
    deps = [dep("a", load=4, capacity=4), dep("b", load=9, capacity=0)]
    decision = sched.evaluate(robot(None), deps, fast())
    assert decision is not None
    assert (decision.to_deployment, decision.reason) == ("b", Reason.INITIAL)


def test_draining_or_timing_out_robots_are_not_refused(sched: Scheduler) -> None:
    # Those robots still have a deployment that answers: admission only concerns placement.
    deps = [dep("a", load=0, capacity=4, draining=True), dep("b", load=4, capacity=4)]
    decision = sched.evaluate(robot("a"), deps, fast())
    assert decision is not None and decision.reason is Reason.DRAIN
