"""A robot frame's accounting, without a network: how a cloud call's round trip splits into
transfer and cloud time (`RemoteTimes`), the telemetry record and the policy's `Outcome` a served
frame hands on (`robotd.frame_path.frame.Frame`), and runs of cloud failures (`FailureRuns`): logged
at their start and end only, a reroute asked after consecutive timeouts or missing routes.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from common.wire.cloud_to_robot import InferReply
from common.wire.telemetry import FallbackReason
from robotd.frame_path.failure_runs import LOG_FAILURE_EVERY, REROUTE_AFTER_FAILURES, FailureRuns
from robotd.frame_path.frame import Frame
from robotd.frame_path.offload import CallResult
from robotd.policies import PURE_ROBOT, Decision
from robotd.telemetry import SERVED_BY_CLOUD, SERVED_BY_ROBOT, RemoteTimes

ROBOT = "robot-1"
DEPLOYMENT = "edge-1"
DEADLINE_S = 0.5
HANDED_AT = 100.0
ROUND_TRIP_S = 0.08
QUEUE_S = 0.01
COMPUTE_S = 0.02
OUTPUTS = {"logits": np.arange(5, dtype=np.float32).reshape(1, 5)}


def answered(epoch: int = 4, queue_s: float = QUEUE_S, compute_s: float = COMPUTE_S) -> CallResult:
    reply = InferReply(
        frame=7,
        deployment=DEPLOYMENT,
        epoch=epoch,
        outputs=OUTPUTS,
        queue_s=queue_s,
        compute_s=compute_s,
    )
    replied_at = HANDED_AT + ROUND_TRIP_S
    return CallResult(
        reply=reply,
        reason=None,
        detail="",
        handed_at=HANDED_AT,
        sent_at=HANDED_AT,
        replied_at=replied_at,
        finished_at=replied_at,
        bytes_down=321,
        deployment=DEPLOYMENT,
    )


def failed(
    reason: FallbackReason, waited_s: float = DEADLINE_S, deployment: str | None = None
) -> CallResult:
    return CallResult(
        reply=None,
        reason=reason,
        detail=f"because {reason}",
        handed_at=HANDED_AT,
        sent_at=HANDED_AT,
        replied_at=None,
        finished_at=HANDED_AT + waited_s,
        bytes_down=0,
        deployment=deployment,
    )


def frame(action: int | str, result: CallResult | None = None, **fields: float) -> Frame:
    f = Frame(
        n=7,
        decision=Decision(action, codec="jpeg80" if action != PURE_ROBOT else "raw"),
        entropy=0.3,
        feeds={},
        started=HANDED_AT - 0.01,
        cpu_started=0.0,
        epoch=2,
        result=result,
    )
    f.prefix_s, f.latency_s, f.cpu_s = 0.01, 0.1, 0.02
    f.bytes_up = 1000 if action != PURE_ROBOT else 0
    for name, value in fields.items():
        setattr(f, name, value)
    return f


# -- how the round trip splits ---------------------------------------------------------------------
def test_an_answered_call_splits_into_the_network_and_the_deployments_own_time() -> None:
    times = RemoteTimes.of(answered())
    assert times.cloud_s == pytest.approx(QUEUE_S + COMPUTE_S)
    assert times.transfer_s == pytest.approx(ROUND_TRIP_S - QUEUE_S - COMPUTE_S)


def test_a_deployment_reporting_more_time_than_the_round_trip_leaves_no_negative_transfer() -> None:
    assert RemoteTimes.of(answered(queue_s=0.05, compute_s=0.05)).transfer_s == 0.0


def test_without_a_reply_the_whole_wait_counts_as_transfer() -> None:
    assert RemoteTimes.of(failed(FallbackReason.TIMEOUT)) == RemoteTimes(transfer_s=DEADLINE_S)
    assert RemoteTimes.of(None) == RemoteTimes(0.0, 0.0)


# -- what a served frame hands on ------------------------------------------------------------------
def test_an_answered_frame_records_the_reply_and_feeds_its_cost_to_the_policy() -> None:
    result = answered(epoch=4)
    f = frame(2, result)
    f.serve_cloud(result)
    record = f.record(ROBOT, energy_j=0.7)
    assert f.served_by == SERVED_BY_CLOUD and f.outputs.keys() == OUTPUTS.keys()
    assert record.action == "cut:2:jpeg80" and not record.fallback and record.reason is None
    assert record.detail is None
    assert (record.deployment, record.epoch) == (DEPLOYMENT, 4)  # the reply's epoch
    assert (record.bytes_up, record.bytes_down) == (1000, 321)
    assert record.cloud_s == pytest.approx(QUEUE_S + COMPUTE_S)
    assert record.energy_j == 0.7 and record.suffix_local_s == 0.0
    outcome = f.outcome(DEADLINE_S)
    assert outcome.cloud_s == pytest.approx(ROUND_TRIP_S)
    assert outcome.cloud_compute_s == pytest.approx(QUEUE_S + COMPUTE_S)
    assert outcome.waited_s is None and outcome.bytes_up == 1000


def test_a_frame_finished_on_the_robot_is_a_fallback_with_its_reason() -> None:
    f = frame(1, failed(FallbackReason.TIMEOUT), local_s=0.03)
    record = f.record(ROBOT, energy_j=0.1)
    assert f.served_by == SERVED_BY_ROBOT
    assert record.fallback and record.reason is FallbackReason.TIMEOUT and record.deployment is None
    assert record.detail == "because timeout"  # the free text travels apart from the reason
    assert record.epoch == 2  # the route epoch the robot held
    assert record.transfer_s == pytest.approx(DEADLINE_S) and record.cloud_s == 0.0
    assert record.suffix_local_s == pytest.approx(0.03)
    outcome = f.outcome(DEADLINE_S)
    assert outcome.cloud_s is None and outcome.cloud_compute_s is None
    assert outcome.waited_s == DEADLINE_S and outcome.local_s == pytest.approx(0.03)


def test_a_pure_robot_frame_is_neither_offloaded_nor_a_fallback() -> None:
    f = frame(PURE_ROBOT)
    record = f.record(ROBOT, energy_j=0.2)
    assert not f.offloaded and not f.hedged
    assert record.action == "P" and not record.fallback and record.bytes_down == 0
    assert (record.transfer_s, record.cloud_s) == (0.0, 0.0)
    outcome = f.outcome(DEADLINE_S)
    assert outcome.cloud_s is None and outcome.waited_s is None and outcome.bytes_up == 0


# -- runs of failures ------------------------------------------------------------------------------
def test_a_run_of_failures_is_logged_at_its_start_and_end_only(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="robotd")
    runs = FailureRuns(ROBOT)
    for n in range(5):
        assert runs.note(n, failed(FallbackReason.BUSY, deployment=DEPLOYMENT)) is None
    assert runs.note(5, answered()) is None
    assert caplog.messages == [
        f"{ROBOT}: frame 0: cloud failed (busy: because busy); finished on the robot",
        f"{ROBOT}: frame 5 answered by {DEPLOYMENT} again after 5 frame(s) finished on the robot",
    ]
    assert (runs.reason, runs.streak) == (None, 0)


def test_a_long_run_is_logged_again_every_so_many_frames(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="robotd")
    runs = FailureRuns(ROBOT)
    for n in range(LOG_FAILURE_EVERY + 1):
        runs.note(n, failed(FallbackReason.BUSY))
    assert [m.split(":")[1].strip() for m in caplog.messages] == [
        "frame 0",
        f"frame {LOG_FAILURE_EVERY}",
    ]


@pytest.mark.parametrize("reason", [FallbackReason.TIMEOUT, FallbackReason.NO_ROUTE])
def test_consecutive_timeouts_or_missing_routes_call_for_a_reroute(reason: FallbackReason) -> None:
    runs = FailureRuns(ROBOT)
    asked = [runs.note(n, failed(reason)) for n in range(REROUTE_AFTER_FAILURES + 1)]
    assert asked == [None] * (REROUTE_AFTER_FAILURES - 1) + [reason, reason]
    assert runs.streak == REROUTE_AFTER_FAILURES + 1


def test_busy_or_mixed_failures_never_call_for_a_reroute() -> None:
    runs = FailureRuns(ROBOT)
    assert all(runs.note(n, failed(FallbackReason.BUSY)) is None for n in range(10))
    # A new reason starts a new run: two timeouts after busy frames are not three in a row.
    assert [runs.note(n, failed(FallbackReason.TIMEOUT)) for n in range(2)] == [None, None]
    assert runs.note(99, failed(FallbackReason.NO_ROUTE)) is None
