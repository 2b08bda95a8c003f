"""The robot daemon's Prometheus metrics (docs/metrics.md, "robot").

`RobotMetrics.frame` is the one call the frame loop makes per frame (through the telemetry sink,
beside the run summary, so the two count the same frames): frames by action and by which result
served them, fallbacks by reason, queries resent by reason, the end-to-end latency histogram, bytes
sent, stale results dropped and frames answered per deployment. The route (epoch and deployment) is
read at scrape time from the registry link, and the source's own counts (frames it dropped unread
because a newer one arrived, `dropped_stale`, and frames it refused, `rejected_frames`) from the
frame source: the same counters the run summary takes at the end, so the two agree, and the loop
pays nothing.

Per frame: a dict lookup of the label set's child (made once per label set: prometheus_client's
`labels()` builds a key each call), two or three locked increments and one histogram observe, a
few microseconds (benchmarks/metrics_overhead.py; docs/metrics.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily, Metric

from common.metrics import LATENCY_BUCKETS_S, NAMESPACE, ReadCollector
from common.wire.telemetry import FallbackReason, ResendReason, TelemetryRecord

if TYPE_CHECKING:
    from robotd.sources.frame_sources import FrameSource

NO_DEPLOYMENT = "none"
"""The route's deployment label when the registry routes the robot to no deployment (local)."""


class RobotMetrics:
    """The metrics of robot `robot` in `registry`; `route()` gives (deployment or None, epoch),
    `source()` the frame source once it is open (None before)."""

    def __init__(
        self,
        registry: CollectorRegistry,
        robot: str,
        route: Callable[[], tuple[str | None, int]],
        *,
        source: Callable[[], FrameSource | None] = lambda: None,
    ) -> None:
        self.robot = robot
        self._route = route
        self._source = source
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
        self._resends = Counter(
            "resends",
            "Queries of offloaded frames sent again within the frame's deadline because they found "
            "no serving deployment, by reason (no_reply, not_serving).",
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
        self._resends_by = {r: self._resends.labels(robot, r.value) for r in ResendReason}
        registry.register(ReadCollector(self._read_route, "the robot's route"))
        registry.register(ReadCollector(self._read_source, "the frame source's counts"))

    def frame(
        self, record: TelemetryRecord, served_by: str, resends: Sequence[ResendReason] = ()
    ) -> None:
        """Count one completed frame (its telemetry record, which result served it, why each
        resend of its query was made: `CallResult.resends`)."""
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
        for reason in resends:
            self._resends_by[reason].inc()

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

    def _read_source(self) -> Iterator[Metric]:
        source = self._source()
        dropped = CounterMetricFamily(
            f"{NAMESPACE}_robot_dropped_stale_frames",
            "Frames the source dropped unread because a newer one arrived first (a source fed "
            "by others: zenoh, ros2:), as the run summary's dropped_stale.",
            labels=["robot"],
        )
        dropped.add_metric([self.robot], source.dropped_stale if source is not None else 0)
        yield dropped
        # Summed: served at 0 from the start like the other counters, without a series for each
        # of the wire's error codes; the summary and the refusal's log line name the code.
        rejected = CounterMetricFamily(
            f"{NAMESPACE}_robot_rejected_frames",
            "Frames the source received but refused (undecodable, too large), as the run "
            "summary's rejected_frames summed over their error codes.",
            labels=["robot"],
        )
        counts = source.rejected_frames() if source is not None else {}
        rejected.add_metric([self.robot], sum(counts.values()))
        yield rejected


__all__ = ["NO_DEPLOYMENT", "RobotMetrics"]
