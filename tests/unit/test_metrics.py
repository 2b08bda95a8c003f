"""The daemons' Prometheus metrics without a network: what one call counts, in a registry of its
own (two daemons in one process never share one), and the closed vocabularies they map.

The endpoint itself and a running fleet's counters against its telemetry are checked over HTTP
in tests/integration/test_cloudd_metrics.py and tests/e2e/test_metrics.py.
"""

from __future__ import annotations

import time
from typing import Any

from prometheus_client import CollectorRegistry

from cloudd.metrics import (
    NOT_REQUESTS,
    REFUSAL_OUTCOMES,
    CloudMetrics,
    RequestOutcome,
    ServiceReading,
    error_outcome,
)
from cloudd.refusals import RefusalReason
from cloudd.state import RobotServiceState
from common.metrics import new_registry
from common.wire import ErrorCode
from common.wire.registry import DeploymentState
from common.wire.telemetry import FallbackReason, ResendReason, TelemetryRecord
from registry.metrics import RegistryMetrics
from registry.scheduler import Reason
from robotd.metrics import NO_DEPLOYMENT, RobotMetrics
from robotd.sources.frame_sources import FrameSource
from robotd.sources.stereo_frame import CameraFrame

ROBOT = "robot-1"


def record(frame: int, **changes: object) -> TelemetryRecord:
    fields: dict[str, object] = {
        "robot": ROBOT,
        "frame": frame,
        "action": "cut:2",
        "bytes_up": 1000,
        "bytes_down": 10,
        "prefix_s": 0.01,
        "transfer_s": 0.01,
        "cloud_s": 0.01,
        "suffix_local_s": 0.0,
        "latency_s": 0.04,
        "robot_cpu_s": 0.01,
        "energy_j": 0.1,
        "deployment": "edge-1",
        "fallback": False,
        "reason": None,
        "epoch": 1,
        "at": time.time(),
    }
    fields.update(changes)
    return TelemetryRecord(**fields)  # type: ignore[arg-type]


def value(registry: CollectorRegistry, name: str, **labels: str) -> float:
    got = registry.get_sample_value(name, labels)
    return 0.0 if got is None else got


def test_a_robots_frames_are_counted_by_action_served_by_and_reason() -> None:
    registry = new_registry()
    held: dict[str, Any] = {"deployment": "edge-1", "epoch": 3}
    metrics = RobotMetrics(registry, ROBOT, lambda: (held["deployment"], held["epoch"]))
    metrics.frame(record(0), "cloud")
    metrics.frame(record(1, fallback=True, deployment=None, reason=FallbackReason.TIMEOUT), "robot")
    metrics.frame(record(2, action="P", bytes_up=0, deployment=None), "robot")
    metrics.frame(record(3, stale=True), "cloud")
    resent = (ResendReason.NO_REPLY, ResendReason.NO_REPLY)
    metrics.frame(record(4, resends=2), "cloud", resent)
    frames = "elasticfog_robot_frames_total"
    assert value(registry, frames, robot=ROBOT, action="cut:2", served_by="cloud") == 3
    assert value(registry, frames, robot=ROBOT, action="cut:2", served_by="robot") == 1
    assert value(registry, frames, robot=ROBOT, action="P", served_by="robot") == 1
    fallbacks = "elasticfog_robot_fallbacks_total"
    assert value(registry, fallbacks, robot=ROBOT, reason="timeout") == 1
    # Every reason is served from the start, at 0.
    assert registry.get_sample_value(fallbacks, {"robot": ROBOT, "reason": "busy"}) == 0
    resends = "elasticfog_robot_resends_total"
    assert value(registry, resends, robot=ROBOT, reason="no_reply") == 2
    assert registry.get_sample_value(resends, {"robot": ROBOT, "reason": "not_serving"}) == 0
    answered = "elasticfog_robot_answered_frames_total"
    assert value(registry, answered, robot=ROBOT, deployment="edge-1") == 3
    assert value(registry, "elasticfog_robot_sent_bytes_total", robot=ROBOT) == 4000
    assert value(registry, "elasticfog_robot_stale_results_dropped_total", robot=ROBOT) == 1
    assert value(registry, "elasticfog_robot_frame_latency_seconds_count", robot=ROBOT) == 5
    assert value(registry, "elasticfog_robot_route_epoch", robot=ROBOT) == 3
    held["deployment"] = None
    info = "elasticfog_robot_route_info"
    assert value(registry, info, robot=ROBOT, deployment=NO_DEPLOYMENT) == 1


def test_two_robots_in_one_process_keep_their_own_registries() -> None:
    first, second = new_registry(), new_registry()
    RobotMetrics(first, ROBOT, lambda: (None, 0)).frame(record(0), "cloud")
    RobotMetrics(second, ROBOT, lambda: (None, 0))
    frames = "elasticfog_robot_frames_total"
    labels = {"robot": ROBOT, "action": "cut:2", "served_by": "cloud"}
    assert first.get_sample_value(frames, labels) == 1
    assert second.get_sample_value(frames, labels) is None


def test_a_failover_is_a_route_change_off_a_deployment_that_failed() -> None:
    registry = new_registry()
    metrics = RegistryMetrics(registry)
    metrics.route_change(Reason.INITIAL.value, None)
    metrics.route_change(Reason.DEPLOYMENT_LOST.value, "edge-1")
    metrics.route_change(Reason.TIMEOUTS.value, "edge-2")
    metrics.route_change(Reason.DEPLOYMENT_LOST.value, None)  # nothing to fail over from
    metrics.route_change(Reason.DRAIN.value, "edge-1")  # planned, not a failover
    assert value(registry, "elasticfog_registry_failovers_total") == 2
    changes = "elasticfog_registry_route_changes_total"
    assert value(registry, changes, reason="deployment_lost") == 2
    assert registry.get_sample_value(changes, {"reason": "better"}) == 0
    metrics.round(0.002)
    metrics.probe_report()
    assert value(registry, "elasticfog_registry_round_duration_seconds_count") == 1
    assert value(registry, "elasticfog_registry_probe_reports_total") == 1


def test_registry_metrics_off_count_nothing() -> None:
    off = RegistryMetrics(None)
    off.round(0.1)
    off.route_change(Reason.DEPLOYMENT_LOST.value, "edge-1")
    off.probe_report()
    assert not off.enabled


def test_every_refusal_and_error_code_has_an_outcome() -> None:
    # A refusal of no request (the in-flight cap, counted at the service ctl) has no outcome.
    assert set(REFUSAL_OUTCOMES) | NOT_REQUESTS == set(RefusalReason)
    assert not set(REFUSAL_OUTCOMES) & NOT_REQUESTS
    assert error_outcome(ErrorCode.DEADLINE_EXPIRED) is RequestOutcome.EXPIRED
    assert error_outcome(ErrorCode.NOT_SERVING) is RequestOutcome.NOT_SERVING
    assert error_outcome(ErrorCode.INTERNAL) is RequestOutcome.ERROR
    assert error_outcome(None) is RequestOutcome.ERROR


def test_a_deployments_services_are_counted_and_read_apart() -> None:
    # Regression: with several services, one plane's requests, queue and states must not be
    # summed into another's series.
    registry = new_registry()
    readings = [
        ServiceReading(
            "detect",
            {ROBOT: RobotServiceState(DeploymentState.SERVICE, 1)},
            (1, 0, 5),
            "zoo:vgg",
            "ab",
        ),
        ServiceReading("tags", {ROBOT: RobotServiceState()}, None, "mod:fn", ""),
    ]
    metrics = CloudMetrics(
        registry, "edge-1", services=lambda: readings, providers=lambda: ["CPUExecutionProvider"]
    )
    detect, tags = metrics.service("detect"), metrics.service("tags")
    detect.answered(ROBOT, 0.01, 0.02)
    detect.batch(1)
    tags.refused(ROBOT, RefusalReason.QUEUE_FULL)
    requests = "elasticfog_cloud_inference_requests_total"
    both = {"deployment": "edge-1", "robot": ROBOT}
    assert value(registry, requests, service="detect", outcome="ok", **both) == 1
    assert value(registry, requests, service="tags", outcome="busy", **both) == 1
    assert value(registry, requests, service="tags", outcome="ok", **both) == 0
    queue_count = "elasticfog_cloud_inference_queue_duration_seconds_count"
    assert value(registry, queue_count, deployment="edge-1", service="detect") == 1
    pending = "elasticfog_cloud_inference_pending_requests"
    assert value(registry, pending, deployment="edge-1", service="detect") == 1
    assert registry.get_sample_value(pending, {"deployment": "edge-1", "service": "tags"}) is None
    state = "elasticfog_cloud_robot_state"
    assert value(registry, state, service="detect", state="service", **both) == 1
    assert value(registry, state, service="tags", state="standby", **both) == 1
    info = {"service": "tags", "model": "mod:fn", "digest": "", "providers": "CPUExecutionProvider"}
    assert value(registry, "elasticfog_cloud_model_info", deployment="edge-1", **info) == 1


class CountingSource(FrameSource):
    """A source fed by others, reduced to the counts it keeps (dropped and refused frames)."""

    def __init__(self) -> None:
        self.rejected: dict[str, int] = {}

    def read(self) -> CameraFrame:
        raise AssertionError("the metrics never read a frame")

    def rejected_frames(self) -> dict[str, int]:
        return dict(self.rejected)


def test_a_robots_source_counts_are_read_from_the_source_at_scrape_time() -> None:
    """dropped_stale and rejected_frames are the source's counters, the ones the run summary
    takes at the end: 0 before the source is open, then whatever it holds at each scrape."""
    registry = new_registry()
    held: dict[str, FrameSource | None] = {"source": None}
    RobotMetrics(registry, ROBOT, lambda: (None, 0), source=lambda: held["source"])
    dropped = "elasticfog_robot_dropped_stale_frames_total"
    rejected = "elasticfog_robot_rejected_frames_total"
    assert registry.get_sample_value(dropped, {"robot": ROBOT}) == 0
    assert registry.get_sample_value(rejected, {"robot": ROBOT}) == 0
    source = CountingSource()
    held["source"] = source
    source.dropped_stale = 7
    source.rejected = {"too_large": 2, "bad_value": 1}
    assert value(registry, dropped, robot=ROBOT) == 7
    assert value(registry, rejected, robot=ROBOT) == 3
