"""The latency-bounded scheduler: each trigger, the choice, load awareness and no flapping."""

from __future__ import annotations

import itertools
import random
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest

from registry.latency import LatencyBound, LatencyWindows, Source, Stat, WindowStats
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


class FakeClock:
    """Monotonic clock under the test's control."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def advance(self, dt: float) -> None:
        self.now += dt


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def sched(clock: FakeClock) -> Scheduler:
    return Scheduler(BOUND, SchedulerParams(), clock=clock)


def window(value: float, clock: FakeClock, count: int = 20) -> WindowStats:
    return WindowStats.of([value] * count, last_at=clock.now)


def dep(name: str, **kw: object) -> DeploymentView:
    return DeploymentView(id=name, service=SERVICE, **kw)  # type: ignore[arg-type]


def robot(route: str | None, telemetry: WindowStats | None = None, **kw: object) -> RobotView:
    return RobotView(id=ROBOT, service=SERVICE, route=route, telemetry=telemetry, **kw)  # type: ignore[arg-type]


def hold(
    sched: Scheduler,
    clock: FakeClock,
    seconds: float,
    make: Callable[[], tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]],
    step_s: float = 0.125,
) -> RouteDecision | None:
    """Evaluate every `step_s` (exact in binary: no drift) for `seconds`; the first decision."""
    for _ in range(round(seconds / step_s) + 1):
        r, deps, profiles = make()
        decision = sched.evaluate(r, deps, profiles)
        if decision is not None:
            return decision
        clock.advance(step_s)
    return None


# -- choice ----------------------------------------------------------------------------------------
def test_initial_route_is_the_lowest_predicted_deployment_meeting_the_bound(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b"), dep("c")]
    profiles = {"a": window(0.05, clock), "b": window(0.03, clock)}
    decision = sched.evaluate(robot(None), deps, profiles)
    # c, not predicted to meet the bound, is not the initial policy's to pick over b (crowded).
    assert decision == RouteDecision(
        ROBOT, None, "b", Reason.INITIAL, ("b", "a", "c"), 0.03, crowded=("c",)
    )


def test_no_usable_deployment_means_no_initial_route(sched: Scheduler, clock: FakeClock) -> None:
    deps = [
        dep("dead", alive=False),
        dep("draining", draining=True),
        DeploymentView(id="other", service="segment"),
        dep("wrong-model", model_digest="sha256:bb"),
    ]
    assert sched.evaluate(robot(None, model_digest="sha256:aa"), deps, {}) is None
    assert sched.evaluate(robot(None), [], {}) is None


def test_choice_is_load_aware(sched: Scheduler, clock: FakeClock) -> None:
    # a is faster when idle but 3/4 busy: 0.04 * (1 + 0.75) = 0.07 > b's 0.06.
    deps = [dep("a", load=3, capacity=4), dep("b", load=0, capacity=4)]
    profiles = {"a": window(0.04, clock), "b": window(0.06, clock)}
    decision = sched.evaluate(robot(None), deps, profiles)
    assert decision is not None and decision.candidates == ("b", "a")
    assert decision.predicted_s == pytest.approx(0.06)


def test_a_full_deployment_ranks_last(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a", load=4, capacity=4), dep("b", capacity=4), dep("c")]
    profiles = {"a": window(0.01, clock), "b": window(0.09, clock)}
    decision = sched.evaluate(robot(None), deps, profiles)
    assert decision is not None and decision.candidates == ("b", "c", "a")


def test_equal_latency_prefers_the_less_loaded(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a", load=1, capacity=4), dep("b", load=0, capacity=0)]
    profiles = {"a": window(0.0, clock), "b": window(0.0, clock)}
    decision = sched.evaluate(robot(None), deps, profiles)
    assert decision is not None and decision.to_deployment == "b"


def test_when_none_meets_the_bound_the_best_available_is_chosen(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b"), dep("c")]
    profiles = {"a": window(0.3, clock), "b": window(0.2, clock)}
    decision = sched.evaluate(robot(None), deps, profiles)
    assert decision is not None and decision.candidates == ("b", "a", "c")


def test_stale_profiles_count_as_unknown_thin_ones_rank_a_forced_move(
    sched: Scheduler, clock: FakeClock
) -> None:
    old = window(0.01, clock)
    clock.advance(SchedulerParams().profile_max_age_s + 1)
    thin = WindowStats.of([0.02, 0.02], last_at=clock.now)  # fewer than min_probe_samples
    profiles = {"old": old, "thin": thin, "known": window(0.09, clock)}
    decision = sched.evaluate(robot(None), [dep("old"), dep("thin"), dep("known")], profiles)
    assert decision is not None and decision.candidates == ("thin", "known", "old")
    assert decision.predicted_s == pytest.approx(0.02)


def thin(value: float, clock: FakeClock) -> WindowStats:
    """Two probes: what every deployment has 4 s after the robot started (one every 2 s)."""
    return WindowStats.of([value, value], last_at=clock.now)


@pytest.mark.parametrize("cloud_samples", [2, 3])
def test_timeouts_move_to_the_nearest_deployment_while_probes_are_thin(
    sched: Scheduler, clock: FakeClock, cloud_samples: int
) -> None:
    """Regression: with every probe window under min_probe_samples all deployments counted as
    unknown, and a robot timing out on edge-1 went to cloud-1 (67 ms; first by id) instead of
    edge-2 (34 ms), corrected only by a `better` move seconds later."""
    deps = [dep("edge-1"), dep("edge-2"), dep("cloud-1"), dep("cloud-2")]
    profiles = {
        "edge-1": thin(0.011, clock),
        "edge-2": thin(0.034, clock),
        "cloud-1": window(0.067, clock, count=cloud_samples),
    }
    n = SchedulerParams().timeout_count
    decision = sched.evaluate(robot("edge-1", timeouts=n), deps, profiles)
    assert decision is not None and decision.reason is Reason.TIMEOUTS
    assert decision.candidates == ("edge-2", "cloud-1", "cloud-2")
    assert decision.predicted_s == pytest.approx(0.034)


def test_the_same_prediction_prefers_the_thicker_profile(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    decision = sched.evaluate(robot(None), deps, {"a": thin(0.05, clock), "b": window(0.05, clock)})
    assert decision is not None and decision.candidates == ("b", "a")


def test_thin_profiles_never_move_a_served_robot(sched: Scheduler, clock: FakeClock) -> None:
    """A move by choice needs min_probe_samples: two fast probes are no reason to leave."""
    deps = [dep("a"), dep("b")]
    # No improvement move to a thin, much faster b (the hold time passes many times over).
    assert (
        hold(
            sched,
            clock,
            3 * SchedulerParams().improve_hold_s,
            lambda: (
                robot("a", window(0.09, clock)),
                deps,
                {"a": window(0.09, clock), "b": thin(0.01, clock)},
            ),
        )
        is None
    )
    # Nor a violation move when only a thin profile is better.
    assert (
        hold(
            sched,
            clock,
            3 * BOUND.hysteresis_s,
            lambda: (robot("a", window(0.3, clock)), deps, {"b": thin(0.01, clock)}),
        )
        is None
    )
    # The same b with enough probes: the violation moves the robot.
    decision = sched.evaluate(robot("a", window(0.3, clock)), deps, {"b": window(0.01, clock)})
    assert decision is not None and (decision.to_deployment, decision.reason) == (
        "b",
        Reason.BOUND_VIOLATION,
    )


# -- forced triggers -------------------------------------------------------------------------------
def test_deployment_loss_reroutes_at_once_even_right_after_a_switch(
    sched: Scheduler, clock: FakeClock
) -> None:
    sched.record_switch(ROBOT, None, "a", Reason.INITIAL)
    deps = [dep("a", alive=False), dep("b")]
    decision = sched.evaluate(robot("a"), deps, {"b": window(0.05, clock)})
    assert decision is not None
    assert (decision.from_deployment, decision.to_deployment, decision.reason) == (
        "a",
        "b",
        Reason.DEPLOYMENT_LOST,
    )
    # A deployment missing from the snapshot altogether is lost too.
    decision = sched.evaluate(robot("a"), [dep("b")], {})
    assert decision is not None and decision.reason is Reason.DEPLOYMENT_LOST


def test_losing_the_last_deployment_drops_the_route(sched: Scheduler) -> None:
    decision = sched.evaluate(robot("a"), [dep("a", alive=False)], {})
    assert decision == RouteDecision(ROBOT, "a", None, Reason.DEPLOYMENT_LOST)


def test_drain_moves_the_robot_unless_nothing_else_is_there(
    sched: Scheduler, clock: FakeClock
) -> None:
    assert sched.evaluate(robot("a"), [dep("a", draining=True)], {}) is None
    decision = sched.evaluate(robot("a"), [dep("a", draining=True), dep("b")], {})
    assert decision is not None and (decision.to_deployment, decision.reason) == ("b", Reason.DRAIN)


def test_consecutive_timeouts_reroute_at_once(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a"), dep("b")]
    profiles = {"a": window(0.01, clock), "b": window(0.05, clock)}
    n = SchedulerParams().timeout_count
    assert sched.evaluate(robot("a", timeouts=n - 1), deps, profiles) is None
    # Timeouts counted against another deployment (the previous route) do not move the robot.
    assert sched.evaluate(robot("a", timeouts=n, timeouts_on="b"), deps, profiles) is None
    decision = sched.evaluate(robot("a", timeouts=n, timeouts_on="a"), deps, profiles)
    assert decision is not None
    assert (decision.to_deployment, decision.reason, decision.candidates) == (
        "b",
        Reason.TIMEOUTS,
        ("b",),
    )
    sched.record_switch(ROBOT, "a", "b", Reason.TIMEOUTS)
    assert sched.penalized(ROBOT) == {"a"}
    # The only other deployment times out too: nothing better to go to, stay.
    assert sched.evaluate(robot("b", timeouts=n), [dep("b")], {}) is None


def test_timeouts_move_only_to_a_deployment_with_room(sched: Scheduler, clock: FakeClock) -> None:
    """A robot timing out on a live deployment that has answered it, whose peers are as loaded,
    stays: its deployment is late, not out of reach, and moving would only carry the timeouts
    there and back (16 robots on two overloaded deployments made 50-150 such moves a run). One
    its deployment never answered on this route (its queries find nobody) still moves."""
    n = SchedulerParams().timeout_count
    profiles = {"a": window(0.01, clock), "b": window(0.05, clock)}
    loaded = [dep("a", load=6, capacity=6), dep("b", load=6, capacity=6)]
    answered = robot("a", timeouts=n, timeouts_on="a", offloaded=10, busy=4)
    assert sched.evaluate(answered, loaded, profiles) is None
    roomy = [dep("a", load=6, capacity=6), dep("b", load=1, capacity=6)]
    for r, deps in ((answered, roomy), (robot("a", timeouts=n, timeouts_on="a"), loaded)):
        decision = sched.evaluate(r, deps, profiles)
        assert decision is not None and (decision.to_deployment, decision.reason) == (
            "b",
            Reason.TIMEOUTS,
        )


def test_a_failed_switch_backs_off_before_deciding_again(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    r = robot("a", timeouts=3)
    assert sched.evaluate(r, deps, {}) is not None
    sched.record_failure(ROBOT)
    clock.advance(0.5)
    assert sched.evaluate(r, deps, {}) is None
    # Losing the deployment is never delayed.
    lost = sched.evaluate(r, [dep("a", alive=False), dep("b")], {})
    assert lost is not None and lost.reason is Reason.DEPLOYMENT_LOST
    clock.advance(SchedulerParams().retry_backoff_s)
    assert sched.evaluate(r, deps, {}) is not None


# -- bound violation -------------------------------------------------------------------------------
def test_violation_must_hold_for_the_hysteresis_time(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a"), dep("b")]
    slow = 0.2

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a", window(slow, clock)), deps, {"b": window(0.05, clock)}

    start = clock.now
    decision = hold(sched, clock, 3.0, make)
    assert decision is not None
    assert (decision.to_deployment, decision.reason) == ("b", Reason.BOUND_VIOLATION)
    assert clock.now - start == pytest.approx(BOUND.hysteresis_s)


def test_an_interrupted_violation_starts_the_hysteresis_over(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    profiles = {"b": window(0.05, clock)}
    assert sched.evaluate(robot("a", window(0.2, clock)), deps, profiles) is None
    clock.advance(0.875)
    assert sched.evaluate(robot("a", window(0.05, clock)), deps, profiles) is None  # a good moment
    clock.advance(0.25)
    profiles = {"b": window(0.05, clock)}
    assert sched.evaluate(robot("a", window(0.2, clock)), deps, profiles) is None
    clock.advance(0.875)
    profiles = {"b": window(0.05, clock)}
    assert sched.evaluate(robot("a", window(0.2, clock)), deps, profiles) is None
    clock.advance(0.125)
    assert sched.evaluate(robot("a", window(0.2, clock)), deps, profiles) is not None


def test_violation_needs_enough_telemetry_samples(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a"), dep("b")]
    few = WindowStats.of([0.5] * (SchedulerParams().min_samples - 1), last_at=clock.now)
    for _ in range(30):
        assert sched.evaluate(robot("a", few), deps, {"b": window(0.05, clock)}) is None
        clock.advance(0.1)


def test_violation_waits_out_the_minimum_dwell_time(sched: Scheduler, clock: FakeClock) -> None:
    deps = [dep("a"), dep("b")]
    sched.record_switch(ROBOT, "b", "a", Reason.BETTER)
    switched_at = clock.now

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a", window(0.2, clock)), deps, {"b": window(0.05, clock)}

    decision = hold(sched, clock, 10.0, make)
    assert decision is not None and decision.reason is Reason.BOUND_VIOLATION
    assert clock.now - switched_at == pytest.approx(SchedulerParams().min_dwell_s)


@pytest.mark.parametrize(
    ("candidate_s", "moves"),
    [
        (0.099, False),  # meets the bound but not better than 0.12 by the 20 % margin
        (0.09, True),  # meets the bound and is better by the margin
        (0.2, False),  # misses the bound and is slower
    ],
)
def test_violation_moves_only_to_a_clearly_better_target(
    sched: Scheduler, clock: FakeClock, candidate_s: float, moves: bool
) -> None:
    deps = [dep("a"), dep("b")]

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a", window(0.12, clock)), deps, {"b": window(candidate_s, clock)}

    decision = hold(sched, clock, 5.0, make)
    assert (decision is not None) is moves


def test_violation_with_none_meeting_takes_the_best_available(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b"), dep("c")]

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        profiles = {"b": window(0.3, clock), "c": window(0.2, clock)}
        return robot("a", window(0.5, clock)), deps, profiles

    decision = hold(sched, clock, 5.0, make)
    assert decision is not None and decision.candidates == ("c", "b")


# -- improvement -----------------------------------------------------------------------------------
def test_a_better_deployment_wins_only_by_the_margin_and_after_the_hold_time(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    params = SchedulerParams()
    b_latency = 0.045  # 10 % better than a's 0.05: within the margin, never worth a move

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a", window(0.05, clock)), deps, {"b": window(b_latency, clock)}

    assert hold(sched, clock, 30.0, make) is None
    b_latency = 0.03  # 40 % better
    start = clock.now
    decision = hold(sched, clock, 30.0, make)
    assert decision is not None
    assert (decision.to_deployment, decision.reason) == ("b", Reason.BETTER)
    assert clock.now - start == pytest.approx(params.improve_hold_s)


def test_a_better_deployment_without_room_to_spare_is_no_target(
    sched: Scheduler, clock: FakeClock
) -> None:
    params = SchedulerParams()
    capacity = 8
    crowded = int(capacity * (1 - params.busy_headroom)) + 1  # past 75%, not full

    def make_with(load: int) -> Callable[[], tuple[RobotView, list[DeploymentView], dict]]:
        deps = [dep("a"), dep("b", load=load, capacity=capacity)]
        return lambda: (robot("a", window(0.05, clock)), deps, {"b": window(0.01, clock)})

    # b is predicted far better even with its load, but a move would crowd it.
    assert hold(sched, clock, 3 * params.improve_hold_s, make_with(crowded)) is None
    decision = hold(sched, clock, 3 * params.improve_hold_s, make_with(crowded - 1))
    assert decision is not None and (decision.to_deployment, decision.reason) == (
        "b",
        Reason.BETTER,
    )


def test_improvement_timer_resets_when_the_advantage_goes(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    b_latency = 0.03

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a", window(0.05, clock)), deps, {"b": window(b_latency, clock)}

    assert hold(sched, clock, 4.0, make) is None
    b_latency = 0.05
    assert hold(sched, clock, 0.125, make) is None
    b_latency = 0.03
    start = clock.now
    decision = hold(sched, clock, 10.0, make)
    assert decision is not None and clock.now - start == pytest.approx(5.0)


def test_without_telemetry_the_current_probe_profile_is_the_reference(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("a"), deps, {"a": window(0.08, clock), "b": window(0.03, clock)}

    decision = hold(sched, clock, 10.0, make)
    assert decision is not None and decision.reason is Reason.BETTER


# -- no return to a deployment left for a violation ------------------------------------------------
def test_a_deployment_left_for_a_violation_must_recover_for_a_while(
    sched: Scheduler, clock: FakeClock
) -> None:
    params = SchedulerParams()
    deps = [dep("a"), dep("b")]
    sched.record_switch(ROBOT, "a", "b", Reason.BOUND_VIOLATION)
    left_at = clock.now
    assert sched.penalized(ROBOT) == {"a"}

    # b now violates (its probes agree); a's probes look good again, but not yet for long.
    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return (
            robot("b", window(0.3, clock)),
            deps,
            {"a": window(0.03, clock), "b": window(0.3, clock)},
        )

    clock.advance(params.min_dwell_s)
    decision = hold(sched, clock, 30.0, make)
    assert decision is not None
    assert (decision.to_deployment, decision.reason) == ("a", Reason.BOUND_VIOLATION)
    # a's probes were good from the first evaluation after the dwell: recovery_s later it is back.
    assert clock.now - left_at == pytest.approx(params.min_dwell_s + params.recovery_s)
    assert sched.penalized(ROBOT) == frozenset()


def test_probes_taken_before_leaving_do_not_count_as_recovery(
    sched: Scheduler, clock: FakeClock
) -> None:
    deps = [dep("a"), dep("b")]
    before = window(0.03, clock)  # last probe of a before the robot left it
    clock.advance(0.1)
    sched.record_switch(ROBOT, "a", "b", Reason.BOUND_VIOLATION)

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("b", window(0.3, clock)), deps, {"a": before}

    assert hold(sched, clock, 8.0, make) is None
    assert sched.penalized(ROBOT) == {"a"}


def test_a_deployment_that_dies_and_returns_starts_clean(
    sched: Scheduler, clock: FakeClock
) -> None:
    sched.record_switch(ROBOT, "a", "b", Reason.TIMEOUTS)
    assert sched.penalized(ROBOT) == {"a"}
    sched.evaluate(robot("b"), [dep("a", alive=False), dep("b")], {})
    assert sched.penalized(ROBOT) == frozenset()


def test_forget_drops_a_robots_memory(sched: Scheduler) -> None:
    sched.record_switch(ROBOT, "a", "b", Reason.BOUND_VIOLATION)
    sched.forget(ROBOT)
    assert sched.penalized(ROBOT) == frozenset()


def test_bad_params_are_refused() -> None:
    with pytest.raises(ValueError, match="min_dwell_s"):
        SchedulerParams(min_dwell_s=-1)
    with pytest.raises(ValueError, match="timeout_count"):
        SchedulerParams(timeout_count=0)
    with pytest.raises(ValueError, match="profile_max_age_s"):
        SchedulerParams(profile_max_age_s=0)


def test_first_violation_move_trusts_telemetry_over_lagging_probes(
    sched: Scheduler, clock: FakeClock
) -> None:
    # a's probe window still shows the time before the delay; the robot's frames are slow now.
    deps = [dep("a"), dep("b")]

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        profiles = {"a": window(0.04, clock), "b": window(0.05, clock)}
        return robot("a", window(0.25, clock)), deps, profiles

    decision = hold(sched, clock, 2.0, make)
    assert decision is not None and decision.to_deployment == "b"


def test_a_second_violation_soon_after_needs_probe_evidence(
    sched: Scheduler, clock: FakeClock
) -> None:
    # The robot's uplink is the bottleneck: frames are slow everywhere, probes fast everywhere.
    params = SchedulerParams()
    deps = [dep("a"), dep("b")]
    sched.record_switch(ROBOT, "a", "b", Reason.BOUND_VIOLATION)
    b_probe = 0.03

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        profiles = {"a": window(0.03, clock), "b": window(b_probe, clock)}
        return robot("b", window(0.3, clock)), deps, profiles

    assert hold(sched, clock, params.flap_window_s - 1.0, make) is None
    # b's own probes turn slow: now there is evidence that b, not the uplink, is the problem.
    b_probe = 0.3
    decision = hold(sched, clock, 1.0 + BOUND.hysteresis_s, make)
    assert decision is not None and decision.to_deployment == "a"


def test_a_second_violation_without_own_probes_stays_until_the_flap_window_ends(
    sched: Scheduler, clock: FakeClock
) -> None:
    params = SchedulerParams()
    deps = [dep("a"), dep("b")]
    sched.record_switch(ROBOT, "a", "b", Reason.BOUND_VIOLATION)
    moved_at = clock.now

    def make() -> tuple[RobotView, list[DeploymentView], dict[str, WindowStats]]:
        return robot("b", window(0.3, clock)), deps, {"a": window(0.03, clock)}

    decision = hold(sched, clock, 2 * params.flap_window_s, make)
    assert decision is not None and decision.to_deployment == "a"
    assert clock.now - moved_at == pytest.approx(params.flap_window_s)


# -- closed loop: steady noisy input, seeded -------------------------------------------------------
FRAME_S = 1 / 30
PROBE_EVERY_S = 0.5
EVALUATE_EVERY_S = 0.1


@dataclass
class World:
    """A robot sending 30 frames/s to its route, probing every deployment twice a second."""

    latency: Callable[[str, float, random.Random], float]
    deployments: tuple[str, ...] = ("a", "b")
    route: str = "a"
    switches: list[tuple[float, str, str, Reason]] = field(default_factory=list)

    def run(self, seconds: float, seed: int, bound: LatencyBound = BOUND) -> None:
        rng = random.Random(seed)
        clock = FakeClock()
        start = clock.now
        sched = Scheduler(bound, clock=clock)
        windows = LatencyWindows(bound.window)
        sched.record_switch(ROBOT, None, self.route, Reason.INITIAL)
        deps = [dep(d) for d in self.deployments]
        ticks = round(seconds / FRAME_S)
        probe_every = round(PROBE_EVERY_S / FRAME_S)
        evaluate_every = round(EVALUATE_EVERY_S / FRAME_S)
        for tick in range(ticks):
            t = clock.now - start
            sample = self.latency(self.route, t, rng)
            windows.add(ROBOT, self.route, Source.TELEMETRY, sample, clock.now)
            if tick % probe_every == 0:
                for d in self.deployments:
                    windows.add(ROBOT, d, Source.PROBE, self.latency(d, t, rng), clock.now)
            if tick % evaluate_every == 0:
                tele = windows.stats(ROBOT, self.route, Source.TELEMETRY)
                decision = sched.evaluate(
                    robot(self.route, tele), deps, windows.profiles(ROBOT, Source.PROBE)
                )
                if decision is not None and decision.to_deployment is not None:
                    self.switches.append((t, self.route, decision.to_deployment, decision.reason))
                    # The daemon's part: a fresh telemetry window for the new route.
                    windows.window(ROBOT, decision.to_deployment, Source.TELEMETRY).clear()
                    sched.record_switch(ROBOT, self.route, decision.to_deployment, decision.reason)
                    self.route = decision.to_deployment
            clock.advance(FRAME_S)


def _gauss(mean: float, sd: float, rng: random.Random) -> float:
    return max(0.0, rng.gauss(mean, sd))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_switch_under_steady_noise_well_within_the_bound(seed: int) -> None:
    world = World(lambda d, t, rng: _gauss(0.05, 0.015, rng))
    world.run(300.0, seed)
    assert world.switches == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_flapping_between_equal_deployments_noisy_around_the_bound(seed: int) -> None:
    # Both hover at the bound: the median breaks it half the time, but moving would buy nothing.
    world = World(lambda d, t, rng: _gauss(0.1, 0.02, rng))
    world.run(300.0, seed)
    assert world.switches == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_heavy_jitter_around_the_bound_moves_rarely_never_back_and_forth(seed: int) -> None:
    # 30 % jitter: an unlucky window can look like a real violation, but after one such move the
    # next needs like-for-like probe evidence, so moves stay a flap window apart.
    world = World(lambda d, t, rng: _gauss(0.1, 0.03, rng))
    world.run(300.0, seed)
    times = [t for t, *_ in world.switches]
    assert len(times) <= 300.0 / SchedulerParams().flap_window_s
    assert all(b - a >= SchedulerParams().flap_window_s for a, b in itertools.pairwise(times))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_injected_delay_moves_once_and_a_clear_recovery_moves_back_once(seed: int) -> None:
    def latency(d: str, t: float, rng: random.Random) -> float:
        if d == "a":
            slow = 0.2 if 60.0 <= t < 120.0 else 0.0
            return _gauss(0.03 + slow, 0.005, rng)
        return _gauss(0.05, 0.01, rng)

    world = World(latency)
    world.run(300.0, seed)
    [(t_out, *move_out), (t_back, *move_back)] = world.switches
    assert move_out == ["a", "b", Reason.BOUND_VIOLATION]
    # Half a window of slow frames to break the median, then the hysteresis time.
    assert 60.0 + BOUND.hysteresis_s <= t_out <= 60.0 + BOUND.hysteresis_s + 0.6
    assert move_back == ["b", "a", Reason.BETTER]
    params = SchedulerParams()
    # a's probe median turns good after half a probe window, then it must stay good for
    # recovery_s before it counts, then be better for improve_hold_s.
    half_probe_window_s = BOUND.window * PROBE_EVERY_S / 2
    earliest = 120.0 + params.recovery_s + params.improve_hold_s
    assert earliest <= t_back <= earliest + half_probe_window_s + 1.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_recovery_within_the_margin_does_not_move_the_robot_back(seed: int) -> None:
    def latency(d: str, t: float, rng: random.Random) -> float:
        if d == "a":
            return _gauss(0.3 if 60.0 <= t < 120.0 else 0.045, 0.005, rng)
        return _gauss(0.05, 0.005, rng)

    world = World(latency)
    world.run(300.0, seed)
    assert [s[1:] for s in world.switches] == [("a", "b", Reason.BOUND_VIOLATION)]
