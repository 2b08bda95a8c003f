"""`elasticfog bench scale`'s per-deployment counts over time: what shows placement by load.

A cell's `timeline` bins the frames each deployment served by when they were sent, from the
load generator's start; `first_served_s` is when each deployment's first reply came; `spread`
says whether every deployment served within the bar (2 s). The bench's fleet puts every robot in
service on edge-1, so any spread is the registry's placement, not the fleet file's.
"""

from __future__ import annotations

from experiments.load_generator import FrameOutcome, FrameRecord
from experiments.scale import (
    SPREAD_WITHIN_S,
    TIMELINE_BIN_S,
    ScaleOptions,
    fallback_reasons,
    fleet_changes,
    spread,
    timeline,
)

START_S = 100.0


def rec(at_s: float, deployment: str, outcome: FrameOutcome = FrameOutcome.SERVED) -> FrameRecord:
    return FrameRecord(
        robot="robot-1",
        frame=0,
        sent_at=START_S + at_s,
        latency_s=0.05,
        outcome=outcome,
        deployment=deployment if outcome is FrameOutcome.SERVED else "",
    )


def test_frames_served_are_binned_per_deployment_from_the_start() -> None:
    records = [
        rec(0.1, "edge-1"),
        rec(0.2, "edge-1"),
        rec(0.7, "edge-2"),
        rec(0.8, "edge-1", FrameOutcome.BUSY),
        rec(1.6, "edge-2"),
    ]
    out = timeline(records, START_S, START_S + 2.0)
    assert out["timeline"] == {
        "bin_s": TIMELINE_BIN_S,
        "served_by_deployment": {"edge-1": [2, 0, 0, 0], "edge-2": [0, 1, 0, 1]},
    }
    assert out["first_served_s"] == {"edge-1": 0.15, "edge-2": 0.75}


def test_spread_needs_every_deployment_within_the_bar() -> None:
    early = {"deployments": 2, "first_served_s": {"edge-1": 0.3, "edge-2": 1.2}}
    late = {"deployments": 2, "first_served_s": {"edge-1": 0.3, "edge-2": SPREAD_WITHIN_S + 0.1}}
    one = {"deployments": 2, "first_served_s": {"edge-1": 0.3}}
    assert spread(early) and not spread(late) and not spread(one)


def test_the_bench_fleet_puts_every_robot_on_the_first_deployment() -> None:
    changes = fleet_changes(ScaleOptions(robots=(4,)), deployments=2, batching=False)
    assert changes["initial_policy"]["edge-1"] == "service"
    assert changes["initial_policy"]["edge-2"] == "standby"


def test_fallbacks_are_told_apart_by_outcome_and_error_code() -> None:
    """Where a cell's fallbacks come from: an error reply by its code (a deadline that passed in
    the deployment's queue is not a timeout), with the robot's wait and when they came."""
    late = FrameRecord("robot-2", 1, START_S + 1.0, 0.501, FrameOutcome.TIMEOUT)
    expired = FrameRecord(
        "robot-3", 1, START_S + 2.0, 0.02, FrameOutcome.ERROR, detail="deadline_expired"
    )
    records = [rec(0.0, "edge-1"), late, expired, rec(3.0, "edge-2")]
    assert fallback_reasons(records) == {
        "error:deadline_expired": {
            "frames": 1,
            "median_wait_s": 0.02,
            "first_at_s": 2.0,
            "last_at_s": 2.0,
        },
        "timeout": {"frames": 1, "median_wait_s": 0.501, "first_at_s": 1.0, "last_at_s": 1.0},
    }
    assert fallback_reasons([rec(0.0, "edge-1")]) == {}
