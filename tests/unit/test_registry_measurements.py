"""registry.measurements without a network: what telemetry and probe reports add to the windows,
when consecutive failures ask for a reroute (once, not on every failed frame past the count),
what a route change or a departure forgets, and that windows come back from the RIB with their
age. Clocks are injected and the RIB lives in memory.
"""

from __future__ import annotations

import math
import threading

import pytest

from common.wire import decode
from common.wire.telemetry import FallbackReason, ProbeReport, TelemetryRecord
from registry.measurements import NO_ROUTE, Measurements
from registry.rib import MEMORY, Rib

ROBOT = "robot-1"
KEY = "ef/unit/tele/robot-1"
DEADLINE_S = 0.5
TIMEOUT_COUNT = 3
WALL_START = 1_700_000_000.0


class Clock:
    """A clock that only moves when told to."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Fixture:
    def __init__(self) -> None:
        self.clock = Clock(100.0)
        self.wall = Clock(WALL_START)
        self.bad: list[tuple[str, str]] = []
        self.m = self.make()

    def make(self) -> Measurements:
        return Measurements(
            5,
            deadline_s=DEADLINE_S,
            timeout_count=TIMEOUT_COUNT,
            on_bad_sample=lambda where, problem: self.bad.append((where, problem)),
            clock=self.clock,
            wall_clock=self.wall,
        )


@pytest.fixture
def f() -> Fixture:
    return Fixture()


def frame(
    deployment: str | None,
    remote_s: float = 0.04,
    *,
    action: str = "cut:1",
    fallback: bool = False,
    reason: FallbackReason | None = None,
    detail: str | None = None,
) -> TelemetryRecord:
    return TelemetryRecord(
        robot=ROBOT,
        frame=0,
        action=action,
        bytes_up=100,
        bytes_down=10,
        prefix_s=0.001,
        transfer_s=remote_s / 2,
        cloud_s=remote_s / 2,
        suffix_local_s=0.0,
        latency_s=remote_s,
        robot_cpu_s=0.001,
        energy_j=0.0,
        deployment=deployment,
        fallback=fallback,
        reason=reason,
        detail=detail,
    )


def probe(deployment: str, rtt_s: float, *, expected_s: float | None = None) -> ProbeReport:
    return ProbeReport(
        robot=ROBOT,
        deployment=deployment,
        ok=True,
        at=WALL_START,
        rtt_s=rtt_s,
        load=1,
        capacity=4,
        expected_latency_s=expected_s,
    )


def test_an_answered_frame_counts_its_remote_part_in_its_deployments_window(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    assert not f.m.record_telemetry(frame("edge-1", 0.04), KEY)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert measures.telemetry is not None
    assert (measures.telemetry.count, measures.telemetry.median) == (1, pytest.approx(0.04))
    status = f.m.robot_status(ROBOT, "edge-1")
    assert (status.action, status.timeouts, status.last_telemetry) == ("cut:1", 0, WALL_START)


def test_a_frame_computed_on_the_robot_measures_no_deployment(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    assert not f.m.record_telemetry(frame(None, 0.0, action="P"), KEY)
    assert f.m.for_scheduler(ROBOT, "edge-1").telemetry is None
    assert f.m.robot_status(ROBOT, "edge-1").action == "P"


def test_consecutive_timeouts_count_the_deadline_and_ask_one_reroute(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    asked = [
        f.m.record_telemetry(frame(None, 0.0, fallback=True, reason=FallbackReason.TIMEOUT), KEY)
        for _ in range(TIMEOUT_COUNT + 2)
    ]
    assert asked == [False, False, True, False, False], "asked once, at the count"
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts_on, measures.timeouts) == ("edge-1", TIMEOUT_COUNT + 2)
    assert measures.telemetry is not None
    assert measures.telemetry.median == DEADLINE_S, "a timeout took at least the deadline"


def test_a_frame_through_the_route_resets_the_failures_and_a_new_reroute_can_be_asked(
    f: Fixture,
) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    timeout = frame(
        None,
        0.0,
        fallback=True,
        reason=FallbackReason.TIMEOUT,
        detail="no reply within 500 ms",
    )
    assert [f.m.record_telemetry(timeout, KEY) for _ in range(TIMEOUT_COUNT)][-1]
    f.m.record_telemetry(frame("edge-1"), KEY)
    assert f.m.for_scheduler(ROBOT, "edge-1").timeouts == 0
    assert [f.m.record_telemetry(timeout, KEY) for _ in range(TIMEOUT_COUNT)][-1]


def test_nobody_serving_the_key_is_a_failure_but_no_latency_sample(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame(None, 0.0, fallback=True, reason=FallbackReason.NO_ROUTE), KEY)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts, measures.telemetry) == (1, None)


def received(record: TelemetryRecord) -> TelemetryRecord:
    """`record` as the registry gets it: encoded by the robot, decoded off the wire."""
    return decode(record.to_wire(), expect=TelemetryRecord)


def test_decoded_timeouts_count_as_failures_and_samples_by_their_member(f: Fixture) -> None:
    """Regression: reasons were matched by their words ("timeout", "no reply"); the registry now
    reads the decoded member, whatever the detail says."""
    f.m.set_route(ROBOT, "edge-1", 1)
    timeout = received(
        frame(None, 0.0, fallback=True, reason=FallbackReason.TIMEOUT, detail="busy queue")
    )
    assert timeout.reason is FallbackReason.TIMEOUT
    asked = [f.m.record_telemetry(timeout, KEY) for _ in range(TIMEOUT_COUNT)]
    assert asked[-1], "the count of decoded timeouts asks for a reroute"
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert measures.timeouts == TIMEOUT_COUNT
    assert measures.telemetry is not None and measures.telemetry.median == DEADLINE_S


def test_a_decoded_no_route_counts_as_a_failure_but_no_sample(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    unserved = received(frame(None, 0.0, fallback=True, reason=FallbackReason.NO_ROUTE))
    assert unserved.reason is FallbackReason.NO_ROUTE
    f.m.record_telemetry(unserved, KEY)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts, measures.telemetry) == (1, None)


@pytest.mark.parametrize(
    "reason", [FallbackReason.BUSY, FallbackReason.ERROR, FallbackReason.OTHER]
)
def test_a_decoded_reason_that_names_no_route_failure_counts_nothing(
    f: Fixture, reason: FallbackReason
) -> None:
    """A detail that reads like a timeout does not make one (nobody matches words)."""
    f.m.set_route(ROBOT, "edge-1", 1)
    other = received(
        frame(None, 0.0, fallback=True, reason=reason, detail="timeout: no reply within 0.2 s")
    )
    f.m.record_telemetry(other, KEY)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts, measures.telemetry) == (0, None)


def test_a_busy_fallback_is_neither_a_failure_nor_a_sample(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame(None, 0.0, fallback=True, reason=FallbackReason.BUSY), KEY)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts, measures.telemetry) == (0, None)


def test_a_route_change_clears_the_new_deployments_window_and_the_failures(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame("edge-2", 0.3), KEY)  # an earlier stay on edge-2
    f.m.record_telemetry(frame(None, 0.0, fallback=True, reason=FallbackReason.TIMEOUT), KEY)
    f.m.set_route(ROBOT, "edge-2", 2)
    measures = f.m.for_scheduler(ROBOT, "edge-2")
    assert (measures.telemetry, measures.timeouts) == (None, 0)
    assert f.m.route(ROBOT) == ("edge-2", 2)
    f.m.set_route(ROBOT, "edge-2", 2)  # confirmed, not changed: the window stays
    f.m.record_telemetry(frame("edge-2", 0.05), KEY)
    f.m.set_route(ROBOT, "edge-2", 2)
    assert f.m.for_scheduler(ROBOT, "edge-2").telemetry is not None


def test_a_reroute_request_counts_at_least_the_timeout_count(f: Fixture) -> None:
    f.m.force_timeouts(ROBOT, "edge-1", 1)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.timeouts_on, measures.timeouts) == ("edge-1", TIMEOUT_COUNT)


def test_probe_reports_feed_the_probe_profiles_and_the_loads(f: Fixture) -> None:
    f.m.record_probe_report(probe("edge-1", 0.08, expected_s=0.03), KEY)
    f.m.record_probe_report(probe("edge-2", 0.05), KEY)
    profiles = f.m.for_scheduler(ROBOT, None).profiles
    assert {d: s.median for d, s in profiles.items()} == {
        "edge-1": pytest.approx(0.03),
        "edge-2": pytest.approx(0.05),
    }, "the robot's estimate when it gives one, else the round trip"
    assert [(p.robot, p.deployment, p.updated_at) for p in f.m.probe_profiles()] == [
        (ROBOT, "edge-1", WALL_START),
        (ROBOT, "edge-2", WALL_START),
    ]
    with Rib(MEMORY) as rib:
        rib.upsert_deployment("edge-1", service="s", model_digest="d", capacity=2, version="1")
        f.m.flush_loads(rib)
        row = rib.deployment("edge-1")
        assert row is not None and (row.load, row.capacity) == (1, 4)
        assert rib.deployment("edge-2") is None, "a deployment the RIB does not know is skipped"


def test_a_bad_number_is_reported_and_leaves_the_window_alone(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame("edge-1", 0.04), KEY)
    f.m.record_telemetry(frame("edge-1", math.nan), KEY)
    assert len(f.bad) == 1
    where, problem = f.bad[0]
    assert where == f"telemetry on {KEY}" and "finite" in problem
    stats = f.m.for_scheduler(ROBOT, "edge-1").telemetry
    assert stats is not None and stats.count == 1


def test_windows_survive_a_restart_with_their_age(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame("edge-1", 0.04), KEY)
    f.m.record_probe_report(probe("edge-2", 0.05), KEY)
    with Rib(MEMORY) as rib:
        rib.reserve_epoch(ROBOT)
        rib.set_route(ROBOT, "edge-1", 1, reason="initial")
        assert f.m.save(rib) == 2
        assert f.m.save(rib) == 0, "only windows changed since the last save"

        f.wall.now += 30.0  # the registry comes back 30 s later, on another monotonic clock
        f.clock.now = 5.0
        again = f.make()
        again.restore(rib)
    assert again.route(ROBOT) == ("edge-1", 1)
    assert again.routes_known() == 1
    [restored] = again.probe_profiles()
    assert (restored.deployment, restored.stats.count) == ("edge-2", 1)
    assert restored.stats.last_at == pytest.approx(5.0 - 30.0), "its age is kept"
    assert restored.updated_at == WALL_START
    telemetry = again.for_scheduler(ROBOT, "edge-1").telemetry
    assert telemetry is not None and telemetry.median == pytest.approx(0.04)


def test_a_deployment_that_left_is_forgotten_and_not_saved_again(f: Fixture) -> None:
    f.m.record_probe_report(probe("edge-2", 0.05), KEY)
    f.m.forget_deployment("edge-2")
    assert f.m.probe_profiles() == []
    with Rib(MEMORY) as rib:
        rib.upsert_deployment("edge-2", service="s", model_digest="d", capacity=2, version="1")
        assert f.m.save(rib) == 0
        f.m.flush_loads(rib)
        row = rib.deployment("edge-2")
        assert row is not None and row.load == 0, "its last load report went with it"


def test_a_robot_that_left_loses_its_windows_and_failures(f: Fixture) -> None:
    f.m.set_route(ROBOT, "edge-1", 1)
    f.m.record_telemetry(frame("edge-1"), KEY)
    f.m.record_telemetry(frame(None, 0.0, fallback=True, reason=FallbackReason.TIMEOUT), KEY)
    f.m.forget_robot(ROBOT)
    measures = f.m.for_scheduler(ROBOT, "edge-1")
    assert (measures.telemetry, measures.timeouts, measures.profiles) == (None, 0, {})
    assert f.m.route(ROBOT) == ("edge-1", 1), "the route stays (the RIB keeps it too)"


def test_no_route_until_one_is_set(f: Fixture) -> None:
    assert f.m.route(ROBOT) == NO_ROUTE
    # Without a route a failure is nobody's: nothing counted, nothing asked.
    assert not f.m.record_telemetry(
        frame(None, 0.0, fallback=True, reason=FallbackReason.TIMEOUT), KEY
    )
    assert f.m.for_scheduler(ROBOT, None).timeouts == 0


def test_callback_threads_and_the_control_loop_at_once(f: Fixture) -> None:
    """Telemetry from several threads while the route changes and windows are saved: every
    sample lands in the window of the deployment it names, and nothing raises."""
    errors: list[BaseException] = []
    frames_per_thread = 200

    def publish(deployment: str) -> None:
        try:
            for _ in range(frames_per_thread):
                f.m.record_telemetry(frame(deployment, 0.02), KEY)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=publish, args=(d,)) for d in ("edge-1", "edge-2")]
    with Rib(MEMORY) as rib:
        for thread in threads:
            thread.start()
        for epoch in range(1, 50):
            f.m.set_route(ROBOT, "edge-1", epoch)
            f.m.save(rib)
        for thread in threads:
            thread.join(10)
    assert not errors and not any(t.is_alive() for t in threads)
    stats = f.m.for_scheduler(ROBOT, "edge-2").telemetry
    assert stats is not None and stats.count == 5, "edge-2's window is full (size 5)"


def test_a_robot_in_a_pool_counts_on_every_member_for_the_next_placement(f: Fixture) -> None:
    f.m.set_route("robot-a", "edge-1", 1, ("edge-1", "edge-2"))
    f.m.for_scheduler("robot-b", "edge-1")
    assert f.m.for_scheduler("robot-new", None).routed == {"edge-1": 2, "edge-2": 1}
    # The round reads the RIB again: the pool shrank to its first member.
    f.m.for_scheduler("robot-a", "edge-1", ("edge-1",))
    assert f.m.for_scheduler("robot-new", None).routed == {"edge-1": 2}
    f.m.forget_robot("robot-a")
    assert f.m.for_scheduler("robot-new", None).routed == {"edge-1": 1}


def test_a_restored_route_of_a_robot_not_back_holds_no_room(f: Fixture) -> None:
    f.m.set_route("robot-away", "edge-1", 3, None)
    assert f.m.route("robot-away") == ("edge-1", 3), "the route is known"
    assert f.m.for_scheduler("robot-new", None).routed == {}, "but counted nowhere"
    f.m.for_scheduler("robot-away", "edge-1")  # back: a round sees it
    assert f.m.for_scheduler("robot-new", None).routed == {"edge-1": 1}


def test_a_save_can_take_the_longest_unsaved_windows_first(f: Fixture) -> None:
    for dep in ("edge-1", "edge-2", "edge-3"):
        f.m.record_probe_report(probe(dep, 0.05), KEY)
    f.m.record_probe_report(probe("edge-1", 0.06), KEY)  # changed again: keeps its turn
    with Rib(MEMORY) as rib:
        assert f.m.unsaved == 3
        assert f.m.save(rib, limit=2) == 2
        assert {p.deployment for p in rib.profiles()} == {"edge-1", "edge-2"}
        assert f.m.unsaved == 1
        assert f.m.save(rib, limit=5) == 1 and f.m.unsaved == 0
