"""Placement by load: a robot's first placement goes to the deployment with the most headroom (the
least committed share of its capacity) among those meeting the bound, not to the first. Robots
routed to a deployment count at once (reported loads lag), the initial policy's choice only breaks
ties, and a fleet whose every robot is in service on one deployment spreads from the first robot:
one each in turn."""

from __future__ import annotations

from collections import Counter
from typing import Any

import pytest

from common.config import FleetConfig, fleet_from_dict
from registry.latency import LatencyBound, Stat, WindowStats
from registry.measurements import Measurements
from registry.round_inputs import prefer_initial, robot_view
from registry.scheduler import (
    DeploymentTable,
    DeploymentView,
    Reason,
    RobotView,
    RouteDecision,
    Scheduler,
    SchedulerParams,
)

SERVICE = "vision"
BOUND = LatencyBound(stat=Stat.MEDIAN, seconds=0.1, hysteresis_s=1.0, better_margin=0.2)
NOW_S = 1000.0
# The deployments: 2 workers, no batching, 4 queue slots.
CAPACITY = 6


@pytest.fixture
def sched() -> Scheduler:
    return Scheduler(BOUND, SchedulerParams(), clock=lambda: NOW_S)


def dep(name: str, load: int = 0, capacity: int = CAPACITY) -> DeploymentView:
    return DeploymentView(id=name, service=SERVICE, load=load, capacity=capacity)


def new_robot(routed: dict[str, int] | None = None, name: str = "robot-1") -> RobotView:
    return RobotView(id=name, service=SERVICE, route=None, routed=routed or {})


def probes(**median_s: float) -> dict[str, WindowStats]:
    return {d: WindowStats.of([s] * 10, last_at=NOW_S) for d, s in median_s.items()}


def fleet(robots: int) -> FleetConfig:
    """The issue's fleet: every robot in service on edge-1, edge-2 in standby."""
    names = [f"robot-{i}" for i in range(1, robots + 1)]
    machines: dict[str, Any] = {"edge-1": {"role": "cloud"}, "edge-2": {"role": "cloud"}}
    machines.update({r: {"role": "robot"} for r in names})
    policy: dict[str, Any] = {r: "robot" for r in names}
    policy["edge-1"] = "service"
    return fleet_from_dict(
        {
            "service": SERVICE,
            "model": "zoo:vgg",
            "latency_bound": {"seconds": 0.1},
            "deadline_s": 0.5,
            "machines": machines,
            "initial_policy": policy,
        }
    )


# -- the scheduler ----------------------------------------------------------------------------
def test_with_room_everywhere_the_rank_decides_and_nothing_is_crowded(sched: Scheduler) -> None:
    decision = sched.evaluate(new_robot(), [dep("a"), dep("b")], probes(a=0.03, b=0.02))
    assert decision is not None
    assert (decision.to_deployment, decision.candidates, decision.crowded) == (
        "b",
        ("b", "a"),
        (),
    )


def test_robots_routed_count_although_the_reported_load_is_zero(sched: Scheduler) -> None:
    # Regression: the reported load is seconds old, so every robot of a round saw room on the
    # fastest deployment and all went there.
    robot = new_robot({"b": 5})
    decision = sched.evaluate(robot, [dep("a"), dep("b")], probes(a=0.03, b=0.02))
    assert decision is not None
    assert (decision.to_deployment, decision.candidates, decision.crowded) == (
        "a",
        ("a", "b"),
        ("b",),
    )


def test_the_reported_load_counts_when_it_is_more_than_the_robots_routed(
    sched: Scheduler,
) -> None:
    decision = sched.evaluate(new_robot({"b": 1}), [dep("a"), dep("b", load=5)], probes())
    assert decision is not None and decision.crowded == ("b",)


def test_the_most_headroom_comes_first_and_the_others_are_crowded(sched: Scheduler) -> None:
    # Regression: the first deployment took robots until 75% committed while the other idled.
    deps = [dep("a", capacity=4), dep("b", capacity=4)]
    decision = sched.evaluate(new_robot({"a": 1}), deps, probes(a=0.02, b=0.03))
    assert decision is not None
    assert (decision.to_deployment, decision.crowded) == ("b", ("a",))
    tied = sched.evaluate(new_robot({"a": 1, "b": 1}), deps, probes(a=0.02, b=0.03))
    assert tied is not None and (tied.to_deployment, tied.crowded) == ("a", ())


def test_headroom_is_a_share_of_each_capacity(sched: Scheduler) -> None:
    deps = [dep("small", capacity=4), dep("large", capacity=12)]
    decision = sched.evaluate(new_robot({"small": 1, "large": 2}), deps, probes())
    assert decision is not None and decision.to_deployment == "large"  # 1/6 < 1/4 taken


def test_meeting_the_bound_comes_before_headroom(sched: Scheduler) -> None:
    decision = sched.evaluate(new_robot({"a": 2}), [dep("a"), dep("b")], probes(a=0.02, b=0.5))
    assert decision is not None and decision.to_deployment == "a"
    assert decision.crowded == ("b",)


def test_room_to_spare_is_below_three_quarters_of_the_capacity(sched: Scheduler) -> None:
    deps = [dep("a", capacity=4), dep("b", capacity=4)]
    below = sched.evaluate(new_robot({"a": 2, "b": 2}), deps, probes(a=0.02, b=0.03))
    at = sched.evaluate(new_robot({"a": 3, "b": 3}), deps, probes(a=0.02, b=0.03))
    assert below is not None and below.crowded == () and below.to_deployment == "a"
    assert at is not None and set(at.crowded) == {"a", "b"}


def test_with_room_nowhere_the_least_committed_comes_first(sched: Scheduler) -> None:
    decision = sched.evaluate(new_robot({"a": 5, "b": 6}), [dep("a"), dep("b")], probes())
    assert decision is not None
    assert decision.to_deployment == "a" and set(decision.crowded) == {"a", "b"}
    # Meeting the bound still comes before a lower share.
    decision = sched.evaluate(
        new_robot({"a": 7, "b": 5}), [dep("a"), dep("b")], probes(a=0.02, b=0.5)
    )
    assert decision is not None and decision.to_deployment == "a"


def test_unknown_capacity_always_has_room(sched: Scheduler) -> None:
    decision = sched.evaluate(new_robot({"a": 50}), [dep("a", capacity=0), dep("b")], probes())
    assert decision is not None and decision.crowded == ()


def test_admission_still_follows_the_reported_load(sched: Scheduler) -> None:
    # Robots routed are an estimate of load: they make room elsewhere preferred, never a refusal.
    routed = sched.evaluate(new_robot({"a": 9, "b": 9}), [dep("a"), dep("b")], probes())
    assert routed is not None and routed.reason is Reason.INITIAL
    full = sched.evaluate(new_robot(), [dep("a", load=6), dep("b", load=6)], probes())
    assert full == RouteDecision("robot-1", None, None, Reason.NO_CAPACITY)


def test_a_lost_deployment_is_not_a_placement_by_load(sched: Scheduler) -> None:
    robot = RobotView(id="robot-1", service=SERVICE, route="gone", routed={"a": 5})
    deps = [DeploymentView(id="gone", service=SERVICE, alive=False), dep("a"), dep("b")]
    decision = sched.evaluate(robot, deps, probes(a=0.02, b=0.03))
    assert decision is not None and decision.reason is Reason.DEPLOYMENT_LOST
    assert decision.crowded == ()


# -- initial_policy's preference ------------------------------------------------------------------
def test_the_initial_policy_wins_while_its_choice_has_room() -> None:
    cfg = fleet(1)
    decision = RouteDecision("robot-1", None, "edge-2", Reason.INITIAL, ("edge-2", "edge-1"), 0.02)
    preferred = prefer_initial(cfg, decision)
    assert (preferred.to_deployment, preferred.candidates) == ("edge-1", ("edge-1", "edge-2"))


def test_the_initial_policy_gives_way_when_its_choice_is_crowded() -> None:
    cfg = fleet(1)
    decision = RouteDecision(
        "robot-1", None, "edge-2", Reason.INITIAL, ("edge-2", "edge-1"), 0.02, ("edge-1",)
    )
    assert prefer_initial(cfg, decision) == decision


# -- a round, as the registry daemon runs it -------------------------------------------------------
def place_all(robots: int) -> Counter[str]:
    """Place every robot of the issue's fleet one after another in one round, as the daemon does:
    measures, scheduler, initial preference, route set. The loads reported are still zero."""
    cfg = fleet(robots)
    sched = Scheduler(BOUND, SchedulerParams(), clock=lambda: NOW_S)
    measurements = Measurements(
        BOUND.window, deadline_s=0.5, timeout_count=3, on_bad_sample=lambda w, p: None
    )
    table = DeploymentTable([dep("edge-1"), dep("edge-2")])
    placed: Counter[str] = Counter()
    for epoch, robot in enumerate(cfg.robot_ids, start=1):
        measures = measurements.for_scheduler(robot, None)
        view = robot_view(robot, None, None, measures, default_service=SERVICE, model_digest=None)
        decision = sched.evaluate(view, table, measures.profiles)
        assert decision is not None and decision.reason is Reason.INITIAL
        final = prefer_initial(cfg, decision)
        assert final.to_deployment is not None
        measurements.set_route(robot, final.to_deployment, epoch)
        placed[final.to_deployment] += 1
    return placed


def test_eight_robots_in_service_on_one_deployment_spread_from_the_first() -> None:
    # Regression (issue 26): edge-1 took 5 robots before edge-2 got one. Now one each in turn,
    # the initial policy's edge-1 first (it breaks the tie of two empty deployments).
    assert place_all(8) == Counter({"edge-1": 4, "edge-2": 4})


def test_sixteen_robots_are_shared_evenly() -> None:
    assert place_all(16) == Counter({"edge-1": 8, "edge-2": 8})


def test_a_few_robots_spread_too_the_initial_policy_breaking_ties() -> None:
    assert place_all(3) == Counter({"edge-1": 2, "edge-2": 1})
    assert place_all(1) == Counter({"edge-1": 1})


# -- counting robots routed ----------------------------------------------------------------------
def test_robots_are_counted_where_routed_until_they_leave() -> None:
    m = Measurements(BOUND.window, deadline_s=0.5, timeout_count=3, on_bad_sample=lambda w, p: None)
    m.set_route("r1", "edge-1", 1)
    m.set_route("r2", "edge-1", 1)
    m.set_route("r2", "edge-2", 2)
    assert m.for_scheduler("new", None).routed == {"edge-1": 1, "edge-2": 1}
    m.forget_robot("r1")
    m.set_route("r2", None, 3)
    assert m.for_scheduler("new", None).routed == {}
    # A robot that came back is counted on its route of record when the scheduler reads it.
    assert m.for_scheduler("r1", "edge-1").routed == {}, "only a robot to be placed reads it"
    assert m.for_scheduler("new", None).routed == {"edge-1": 1}
