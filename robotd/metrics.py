"""The robot daemon's Prometheus metrics (docs/metrics.md, "robot").

`RobotMetrics.frame` is the one call the frame loop makes per frame (through the telemetry sink,
beside the run summary, so the two count the same frames): frames by action and by which result
served them, fallbacks by reason, the end-to-end latency histogram, bytes sent, stale results
dropped and frames answered per deployment. The route (epoch and deployment) is read at scrape
time from the registry link, so it costs the loop nothing.

Per frame: a dict lookup of the label set's child (made once per label set: prometheus_client's
`labels()` builds a key each call), two or three locked increments and one histogram observe, a
few microseconds (benchmarks/metrics_overhead.py; docs/metrics.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, InfoMetricFamily, Metric

from common.metrics import LATENCY_BUCKETS_S, NAMESPACE, ReadCollector
from common.wire.telemetry import FallbackReason, TelemetryRecord

NO_DEPLOYMENT = "none"
"""The route's deployment label when the registry routes the robot to no deployment (local)."""


class RobotMetrics:
    """The metrics of robot `robot` in `registry`; `route()` gives (deployment or None, epoch)."""

    def __init__(
        self,
        registry: CollectorRegistry,
        robot: str,
        route: Callable[[], tuple[str | None, int]],
    ) -> None:
        self.robot = robot
        self._route = route
        ns = NAMESPACE
        self._frames = Counter(
            "frames",
            "Frames completed, by action (P or cut:K[:codec]) and by which result served them "
            "(cloud or robot).",
            ["robot", "action", "served_by"],
            namespace=ns,
            subsystem="robot",
            registry=registry,
        )
        self._fallbacks = Counter(
            "fallbacks",
            "Offloaded frames the robot finished itself, by reason.",
            ["robot", "reason"],
            namespace=ns,
            subsystem="robot",
            registry=registry,
        )
        self._answered = Counter(
            "answered_frames",
            "Offloaded frames answered by a deployment, by deployment.",
            ["robot", "deployment"],
            namespace=ns,
            subsystem="robot",
            registry=registry,
        )
        self._latency = Histogram(
            "frame_latency_seconds",
            "End-to-end latency of a frame: from its start to its result, seconds.",
            ["robot"],
            namespace=ns,
            subsystem="robot",
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        ).labels(robot)
        self._bytes_up = Counter(
            "sent_bytes",
            "Bytes of requests sent to the cloud (encoded cut tensors).",
            ["robot"],
            namespace=ns,
            subsystem="robot",
            registry=registry,
        ).labels(robot)
        self._stale = Counter(
            "stale_results_dropped",
            "Results dropped because a newer frame's had been applied (frames in flight).",
            ["robot"],
            namespace=ns,
            subsystem="robot",
            registry=registry,
        ).labels(robot)
        # Children per label set, made on first use (labels() costs a tuple and a lock a call).
        self._frames_by: dict[tuple[str, str], Counter] = {}
        self._fallbacks_by: dict[str, Counter] = {}
        self._answered_by: dict[str, Counter] = {}
        # Every reason served from the start, at 0: a rate over a series that appears only
        # with its first fallback would miss that one (Prometheus: initialize known labels).
        for known in FallbackReason:
            self._fallbacks_by[known.value] = self._fallbacks.labels(robot, known.value)
        registry.register(ReadCollector(self._read_route, "the robot's route"))

    def frame(self, record: TelemetryRecord, served_by: str) -> None:
        """Count one completed frame (its telemetry record, which result served it)."""
        key = (record.action, served_by)
        frames = self._frames_by.get(key)
        if frames is None:
            frames = self._frames_by[key] = self._frames.labels(self.robot, *key)
        frames.inc()
        self._latency.observe(record.latency_s)
        if record.bytes_up:
            self._bytes_up.inc(record.bytes_up)
        if record.fallback:
            reason = record.reason.value if record.reason is not None else "unknown"
            fallbacks = self._fallbacks_by.get(reason)
            if fallbacks is None:
                fallbacks = self._fallbacks_by[reason] = self._fallbacks.labels(self.robot, reason)
            fallbacks.inc()
        elif record.deployment is not None:
            answered = self._answered_by.get(record.deployment)
            if answered is None:
                answered = self._answered.labels(self.robot, record.deployment)
                self._answered_by[record.deployment] = answered
            answered.inc()
        if record.stale:
            self._stale.inc()

    def _read_route(self) -> Iterator[Metric]:
        deployment, epoch = self._route()
        g = GaugeMetricFamily(
            f"{NAMESPACE}_robot_route_epoch",
            "Epoch of the route the robot holds (the registry's last word on who serves it).",
            labels=["robot"],
        )
        g.add_metric([self.robot], epoch)
        yield g
        info = InfoMetricFamily(
            f"{NAMESPACE}_robot_route",
            "The deployment the registry routes the robot to (none: the robot computes alone).",
            labels=["robot"],
        )
        info.add_metric([self.robot], {"deployment": deployment or NO_DEPLOYMENT})
        yield info


__all__ = ["NO_DEPLOYMENT", "RobotMetrics"]
