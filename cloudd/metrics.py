"""The cloud daemon's Prometheus metrics (docs/metrics.md, "cloud").

Counted where the daemon already decides: `request(robot, outcome)` where a request is refused
(`cloudd.admission`, beside the refusal counts) or answered with an error (`cloudd.batch_runner`),
`answered(robot, queue_s, compute_s)` where a reply with outputs goes out (the outcome `ok` and
the queue and compute histograms, the times the reply itself carries), `batch(size)` where a
batch has run: each service's plane counts through its own `ServiceMetrics`. Read at scrape
time: requests pending and the capacity (each service's queue), each robot's state here (each
service's robot book), the execution providers and each service's model. Every series but the
providers' carries a `service` label: a deployment serving several services has a queue, a
state per robot and a model for each.

Names follow Triton's where the meaning is the same (`inference_request`, `queue_duration`,
`compute_infer_duration`, `pending_request`, `inference_exec`), in Prometheus's base units
(seconds, not Triton's microseconds) and with its suffixes (`_total`, `_seconds`).
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, InfoMetricFamily, Metric

from cloudd.refusals import RefusalReason
from cloudd.state import RobotServiceState
from common.metrics import BATCH_SIZE_BUCKETS, LATENCY_BUCKETS_S, NAMESPACE, ReadCollector
from common.wire import ErrorCode
from common.wire.registry import DeploymentState


class RequestOutcome(str, enum.Enum):
    """What became of an inference request (the `outcome` label)."""

    OK = "ok"  # answered with its outputs
    BUSY = "busy"  # refused at once: queue full, the robot at its in-flight limit, stopping
    ERROR = "error"  # the suffix failed, or an unexpected error (INTERNAL)
    TOO_LARGE = "too_large"  # a payload or tensor over the deployment's limits
    WRONG_ROBOT = "wrong_robot"  # the body names another robot than its key
    BAD_REQUEST = "bad_request"  # does not decode, or does not fit this model
    NOT_SERVING = "not_serving"  # reached a deployment not serving its robot (crossed a switch)
    EXPIRED = "expired"  # its deadline passed in the queue: answered without computing
    DROPPED = "dropped"  # held unanswered by fault injection (drop or stall)
    # An h264 P-frame its robot's decoder here cannot decode: resent as a keyframe.
    NEED_KEYFRAME = "need_keyframe"

    def __str__(self) -> str:
        return self.value


REFUSAL_OUTCOMES = {
    RefusalReason.REQUEST_TOO_LARGE: RequestOutcome.TOO_LARGE,
    RefusalReason.TENSOR_TOO_LARGE: RequestOutcome.TOO_LARGE,
    RefusalReason.ECHO_TOO_LARGE: RequestOutcome.TOO_LARGE,
    RefusalReason.WRONG_ROBOT: RequestOutcome.WRONG_ROBOT,
    RefusalReason.ROBOT_IN_FLIGHT: RequestOutcome.BUSY,
    RefusalReason.QUEUE_FULL: RequestOutcome.BUSY,
    RefusalReason.STOPPING: RequestOutcome.BUSY,
    RefusalReason.BAD_REQUEST: RequestOutcome.BAD_REQUEST,
    RefusalReason.NEED_KEYFRAME: RequestOutcome.NEED_KEYFRAME,
}
"""The outcome of a request refused for each counted reason."""

NOT_REQUESTS = frozenset({RefusalReason.IN_FLIGHT_CAP, RefusalReason.UNKNOWN_SERVICE})
"""Counted refusals that refuse no inference request, so have no outcome: a robot announcing
more frames in flight than the cap is counted once at its service ctl (`cloudd.control`); its
requests past the cap are then refused one by one as `robot_in_flight` (`busy`). A probe or
ctl naming a service not served here (`cloudd.planes`) comes on no service key."""

ERROR_OUTCOMES = {
    ErrorCode.DEADLINE_EXPIRED: RequestOutcome.EXPIRED,
    ErrorCode.NOT_SERVING: RequestOutcome.NOT_SERVING,
}
"""The outcome of an error reply by its code; any other code a worker answers is `error`."""


def error_outcome(code: ErrorCode | None) -> RequestOutcome:
    """The outcome of a request a worker answered with error `code` (None: a code this build
    does not know)."""
    return (
        ERROR_OUTCOMES.get(code, RequestOutcome.ERROR) if code is not None else RequestOutcome.ERROR
    )


@dataclass(frozen=True)
class ServiceReading:
    """What the metrics read of one service's plane at scrape time: each robot's state there,
    (requests pending, requests queued, capacity) of its queue (None before the queue exists),
    and its model (a path, zoo:NAME or a handler's module:function) with its digest ('' before
    it is loaded)."""

    service: str
    states: dict[str, RobotServiceState]
    queue: tuple[int, int, int] | None
    model: str
    digest: str


class CloudMetrics:
    """The metrics of deployment `deployment` in `registry`, every series labelled by service.

    `services()`: a `ServiceReading` of each service the deployment serves, read at scrape time;
    `providers()`: the execution providers the sessions run on. Each service's plane counts
    through its own `service(name)`.
    """

    def __init__(
        self,
        registry: CollectorRegistry,
        deployment: str,
        *,
        services: Callable[[], Sequence[ServiceReading]],
        providers: Callable[[], Sequence[str]],
    ) -> None:
        self.deployment = deployment
        self._services = services
        self._providers = providers
        ns, sub = NAMESPACE, "cloud"
        self._requests = Counter(
            "inference_requests",
            "Inference requests on the robots' service keys, by service, robot and outcome.",
            ["deployment", "service", "robot", "outcome"],
            namespace=ns,
            subsystem=sub,
            registry=registry,
        )
        self._queue_s = Histogram(
            "inference_queue_duration_seconds",
            "Seconds an answered request waited in the queue for a worker.",
            ["deployment", "service"],
            namespace=ns,
            subsystem=sub,
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        )
        self._compute_s = Histogram(
            "inference_compute_infer_duration_seconds",
            "Seconds of the suffix run that computed an answered request (its whole batch's).",
            ["deployment", "service"],
            namespace=ns,
            subsystem=sub,
            buckets=LATENCY_BUCKETS_S,
            registry=registry,
        )
        self._batch = Histogram(
            "inference_batch_size",
            "Requests per model run (1 without batching).",
            ["deployment", "service"],
            namespace=ns,
            subsystem=sub,
            buckets=BATCH_SIZE_BUCKETS,
            registry=registry,
        )
        registry.register(ReadCollector(self._read, "the deployment's queues and states"))

    def service(self, name: str) -> ServiceMetrics:
        """What the plane of service `name` counts through."""
        labels = (self.deployment, name)
        return ServiceMetrics(
            name,
            functools.partial(self._requests.labels, *labels),
            queue_s=self._queue_s.labels(*labels),
            compute_s=self._compute_s.labels(*labels),
            batch=self._batch.labels(*labels),
        )

    # -- read at scrape time -------------------------------------------------------------------
    def _read(self) -> Iterator[Metric]:
        ns, d = NAMESPACE, self.deployment
        readings = list(self._services())
        labels = ["deployment", "service"]
        for name, text, index in (
            (
                "inference_pending_requests",
                "Requests admitted and not answered yet (queued or running).",
                0,
            ),
            ("inference_queued_requests", "Requests waiting for a worker.", 1),
            ("capacity_requests", "Requests admitted at once at most.", 2),
        ):
            g = GaugeMetricFamily(f"{ns}_cloud_{name}", text, labels=labels)
            for r in readings:
                if r.queue is not None:
                    g.add_metric([d, r.service], r.queue[index])
            yield g
        state = GaugeMetricFamily(
            f"{ns}_cloud_robot_state",
            "Each robot's state here, per service: 1 for the state it is in, 0 for the others.",
            labels=["deployment", "service", "robot", "state"],
        )
        for r in readings:
            for robot, st in sorted(r.states.items()):
                for s in DeploymentState:
                    state.add_metric([d, r.service, robot, s.value], 1.0 if st.state is s else 0.0)
        yield state
        providers = tuple(self._providers())
        info = InfoMetricFamily(
            f"{ns}_cloud_model",
            "The model each service of this deployment runs and the execution providers of its "
            "sessions, in order of preference.",
            labels=labels,
        )
        for r in readings:
            info.add_metric(
                [d, r.service],
                {"model": r.model, "digest": r.digest, "providers": ",".join(providers)},
            )
        yield info
        ranks = GaugeMetricFamily(
            f"{ns}_cloud_provider_rank",
            "Each execution provider of the sessions and its rank (0: preferred).",
            labels=["deployment", "provider"],
        )
        for rank, provider in enumerate(providers):
            ranks.add_metric([d, provider], rank)
        yield ranks


class ServiceMetrics:
    """What one service's plane counts, where it decides (see the module docstring); made by
    `CloudMetrics.service`."""

    def __init__(
        self,
        service: str,
        requests: Callable[[str, str], Counter],
        *,
        queue_s: Histogram,
        compute_s: Histogram,
        batch: Histogram,
    ) -> None:
        self.service = service
        self._requests = requests  # (robot, outcome) -> the counter of that series
        self._queue_s = queue_s
        self._compute_s = compute_s
        self._batch = batch
        self._by: dict[tuple[str, RequestOutcome], Counter] = {}

    def request(self, robot: str, outcome: RequestOutcome) -> None:
        """One request of `robot` came to `outcome`."""
        key = (robot, outcome)
        counter = self._by.get(key)
        if counter is None:
            counter = self._by[key] = self._requests(robot, outcome.value)
        counter.inc()

    def refused(self, robot: str, reason: RefusalReason) -> None:
        """One request of `robot` refused for `reason` (as `cloudd.refusals` counts it)."""
        self.request(robot, REFUSAL_OUTCOMES[reason])

    def answered(self, robot: str, queue_s: float, compute_s: float) -> None:
        """One request of `robot` answered with its outputs, after these seconds."""
        self.request(robot, RequestOutcome.OK)
        self._queue_s.observe(queue_s)
        self._compute_s.observe(compute_s)

    def batch(self, size: int) -> None:
        """One model run of `size` requests."""
        self._batch.observe(size)


__all__ = [
    "ERROR_OUTCOMES",
    "NOT_REQUESTS",
    "REFUSAL_OUTCOMES",
    "CloudMetrics",
    "RequestOutcome",
    "ServiceMetrics",
    "ServiceReading",
    "error_outcome",
]
