"""One service's plane on a deployment: everything a cloud daemon keeps per service.

A deployment serves every service the fleet file gives it (`FleetConfig.services_of`), each in a
plane of its own built from the service's view of the fleet (`FleetConfig.for_service`: a
one-service fleet with the service's overrides and only the machines serving or using it), so
the path of a request is the one-service path unchanged: the model (a `SplitModel`, or a
handler's `HandlerModel`: one cut, 0), loaded and warmed (`cloudd.suffixes`); the robot book
(state and epoch per robot, `cloudd.robot_book`) and its controller (`cloudd.control`); the
robots' service keys `svc/<service>/<robot>/infer`, declared only while in service for that
robot (`cloudd.service_keys`); the admission, the batch queue, the workers and the batch
runner. "A deployment may serve robot-1's `detect` and stand by for its `segment`": each
plane has its own state per robot. Each plane gets the machine's `workers` and `queue`.

What the planes share is the deployment's (`DeploymentParts`): the Zenoh session, the fault
injection, the replier and its timer, the limits, the refusal counts, the throttled log and the
`closing` event; the daemon owns them, and the lifecycle (the daemon's `ExitStack`) owns what a
plane makes: the daemon holds its model and releases its workers and service keys.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import zenoh

from cloudd.admission import Admission, Job
from cloudd.batch_queue import BatchCosts, BatchPolicy, FairQueue
from cloudd.batch_runner import BatchRunner
from cloudd.batch_stats import BatchStats
from cloudd.control import Controller
from cloudd.cpu_lanes import UsageMeter, lanes_supported
from cloudd.faults import FaultInjector
from cloudd.limits import CloudLimits
from cloudd.metrics import ServiceMetrics, ServiceReading
from cloudd.refusals import Refusals
from cloudd.replies import Replier
from cloudd.robot_book import RobotBook
from cloudd.service_keys import Guard, ServiceKeys
from cloudd.state import RobotServiceState
from cloudd.suffixes import open_split_model, warm_suffixes
from cloudd.video_streams import VideoDecoders
from cloudd.workers import BatchWorkers
from common.config import FleetConfig, MachineConfig
from common.errors import UserError
from common.handler_model import HandlerModel
from common.handlers import HandlerError
from common.heap import release_freed_memory
from common.partition import TensorSpec
from common.partition.runtime import SplitModel
from common.providers import ProviderCheck
from common.throttled_log import ThrottledLog
from common.wire.registry import PROTOCOL_VERSION, CtlReply, CtlRequest, ProbeReply

log = logging.getLogger(__name__)

INFLIGHT_WAIT_S = 0.4
"""How long shutdown lets admitted requests finish before closing the session."""


@dataclass(frozen=True)
class DeploymentParts:
    """What every plane of one deployment shares (made by the daemon)."""

    deployment: str
    machine: MachineConfig
    capabilities: tuple[str, ...]
    faults: FaultInjector
    replies: Replier
    limits: CloudLimits
    refusals: Refusals
    throttled: ThrottledLog
    closing: threading.Event


@dataclass(frozen=True)
class _Started:
    """What `start` made that queries, control and draining use."""

    session: zenoh.Session
    queue: FairQueue[Job]
    admission: Admission


def model_name(view: FleetConfig) -> str:
    """A service's model as the log and the metrics name it: its path or zoo:NAME, or its
    handler's module:function."""
    return view.model_spec if view.handler is None else view.handler


class ServicePlane:
    """Service `view.service_name` on deployment `parts.deployment` (see the module
    docstring); `who` names it in the log (the deployment, with the service when the deployment
    serves several)."""

    def __init__(self, view: FleetConfig, parts: DeploymentParts, *, who: str) -> None:
        self.view = view
        self.name = view.service_name
        self.who = who
        self._parts = parts
        self.book = RobotBook(view.robot_ids, closing=parts.closing)
        # The robots' h264 streams (decoded at admission; freed when a robot leaves service).
        self.video = VideoDecoders(
            max_streams=parts.limits.video_streams, idle_s=parts.limits.video_idle_s
        )
        self._service_keys = ServiceKeys(view.fleet, self.name, parts.deployment, self.book)
        self.controller = Controller(
            parts.deployment,
            service=self.name,
            book=self.book,
            faults=parts.faults,
            declare_service=self._declare_service,
            refusals=parts.refusals,
            set_in_flight=self._set_in_flight,
            left_service=self.video.forget,
            who=who,
        )
        self._costs = BatchCosts()
        self.batch_stats = BatchStats()
        self.providers: ProviderCheck | None = None
        """The providers the suffix sessions got once warm (`fell_back` with
        `providers_fallback: allow` when they did not get an accelerator asked for)."""
        self.model: SplitModel | None = None
        self.cut_specs: list[list[TensorSpec]] = []
        self._started: _Started | None = None
        self._guard: Guard | None = None

    # -- views -----------------------------------------------------------------------------
    @property
    def model_name(self) -> str:
        """The service's model (path or zoo:NAME) or handler (module:function)."""
        return model_name(self.view)

    def states(self) -> dict[str, RobotServiceState]:
        """Every known robot's state and epoch in this service."""
        return self.book.states()

    def profile(self, echo_bytes: int = 0) -> ProbeReply:
        """What a probe naming this service is answered with."""
        parts = self._parts
        snapshot, served = self.book.snapshot()
        model = self.model
        queue = self._started.queue if self._started is not None else None
        return ProbeReply(
            deployment=parts.deployment,
            protocol_version=PROTOCOL_VERSION,
            capabilities=parts.capabilities,
            service=self.name,
            model_digest=model.digest if model is not None else "",
            states={robot: st.state for robot, st in snapshot.items()},
            load=queue.load if queue is not None else 0,
            capacity=queue.capacity if queue is not None else 0,
            num_cuts=len(self.cut_specs),
            fault=parts.faults.get(),
            echo=bytes(echo_bytes),
            epochs={robot: st.wire_epoch for robot, st in snapshot.items()},
            served=served,
            refused=parts.refusals.snapshot(),
            providers=self.providers.got if self.providers is not None else (),
            providers_fallback=self.providers is not None and self.providers.fell_back,
        )

    def reading(self) -> ServiceReading:
        """What the metrics read of this plane at scrape time."""
        started, model = self._started, self.model
        queue = started.queue if started is not None else None
        return ServiceReading(
            service=self.name,
            states=self.states(),
            queue=(queue.load, queue.queued, queue.capacity) if queue is not None else None,
            model=self.model_name,
            digest=model.digest if model is not None else "",
        )

    def control(self, request: CtlRequest) -> CtlReply:
        """Carry out a control request naming this service."""
        return self.controller.control(request)

    def describe(self, policy: BatchPolicy) -> str:
        """The ready line's phrase for this plane."""
        queue = self._started.queue if self._started is not None else None
        batching = (
            f"batches of up to {policy.max_batch} within {policy.max_queue_delay_s * 1000:g} ms"
            if self._parts.machine.batching.enabled
            else "batching off"
        )
        return (
            f"service {self.name!r}, {len(self.cut_specs)} cuts warm, "
            f"{self._parts.machine.workers} workers, "
            f"{queue.capacity if queue is not None else 0} slots, at most "
            f"{policy.max_in_flight_per_robot} per robot, {batching}"
        )

    # -- startup steps ---------------------------------------------------------------------
    def open_model(self) -> SplitModel:
        """The service's model split at its cuts, sessions not built yet (`warm` builds them);
        the daemon holds it. A handler that fails its first call is a UserError."""
        log.info("%s: loading %s", self.who, self.model_name)
        try:
            self.model = open_split_model(self.view, self._parts.machine)
        except HandlerError as exc:
            raise UserError(f"service {self.name!r}: {exc}") from None
        return self.model

    def warm(self, stop: threading.Event) -> bool:
        """Build and run every suffix of the opened model once; False when `stop` was set
        meanwhile."""
        model, parts = self.model, self._parts
        assert model is not None, "open_model() first"
        started = time.monotonic()
        warm = warm_suffixes(
            model, parts.machine, deployment=self.who, model_name=self.model_name, stop=stop
        )
        if warm is None:
            return False
        # The warm-up's first runs allocate tensor by tensor and glibc keeps what they freed;
        # later runs take one planned block each, so giving it back now is not undone.
        release_freed_memory(parts.deployment)
        self.cut_specs = cut_specs = warm.cut_specs
        self.providers = warm.providers
        oversized = parts.limits.oversized_tensors(cut_specs)
        if oversized:
            log.warning(
                "%s: %s over limits.max_tensor_bytes (%d bytes): requests for these cuts will "
                "be refused",
                self.who,
                ", ".join(oversized),
                parts.limits.tensor_bytes,
            )
        took_s = time.monotonic() - started
        if isinstance(model, HandlerModel):
            outputs = model.handler.outputs or {}
            log.info(
                "%s: handler %s (%s) loaded: image %s, outputs %s, in %.1f s",
                self.who,
                self.model_name,
                model.digest[:12],
                "x".join(map(str, cut_specs[0][0].shape)),
                ", ".join(f"{n}:{d}" for n, d in outputs.items()),
                took_s,
            )
            return True
        log.info(
            "%s: model %s (%s) loaded: %d cuts, %.1f MB of weights, on %s, in %.1f s",
            self.who,
            model.partition.model,
            model.digest[:12],
            model.num_cuts,
            model.weight_bytes / 1e6,
            ", ".join(warm.providers.got),
            took_s,
        )
        return True

    def start(
        self,
        session: zenoh.Session,
        policy: BatchPolicy,
        guard: Guard,
        metrics: ServiceMetrics | None,
    ) -> BatchWorkers[Job]:
        """The queue, the workers running its batches and the service keys' admission, on
        `session`; the daemon stops the workers (`stop_workers`) at shutdown."""
        parts, model = self._parts, self.model
        assert model is not None, "open_model() first"
        machine = parts.machine
        # Each worker may run a whole batch; `queue` slots wait beyond that.
        slots = machine.workers * policy.max_batch + machine.queue
        queue: FairQueue[Job] = FairQueue(
            policy, slots=slots, costs=self._costs, batchable=model.batched
        )
        admission = Admission(
            parts.deployment,
            digest=model.digest,
            cut_specs=self.cut_specs,
            queue=queue,
            book=self.book,
            faults=parts.faults,
            replies=parts.replies,
            limits=parts.limits,
            refusals=parts.refusals,
            throttled=parts.throttled,
            metrics=metrics,
            video=self.video,
            who=self.who,
        )
        runner = BatchRunner(
            parts.deployment,
            model=model,
            cut_specs=self.cut_specs,
            queue=queue,
            costs=self._costs,
            stats=self.batch_stats,
            book=self.book,
            replies=parts.replies,
            closing=parts.closing,
            throttled=parts.throttled,
            metrics=metrics,
            who=self.who,
        )
        yields = machine.batching.heavy_robots_low_priority and lanes_supported()
        workers = BatchWorkers(
            queue,
            runner.run,
            machine.workers,
            name=f"{parts.deployment}-{self.name}-worker",
            meter=UsageMeter() if yields else None,
        )
        workers.start()
        self._guard = guard
        self._started = _Started(session=session, queue=queue, admission=admission)
        return workers

    # -- service keys ----------------------------------------------------------------------
    def _set_in_flight(self, robot: str, announced: int) -> int | None:
        """The Controller passes on the frames in flight a robot announced; the limit now in
        force for it (None before the queue exists)."""
        started = self._started
        return None if started is None else started.queue.set_in_flight(robot, announced)

    def _declare_service(self, robot: str) -> None:
        """Declare `robot`'s service keys of this service (`cloudd.service_keys`; the
        Controller calls this before acking service)."""
        started, guard = self._started, self._guard
        if started is None or guard is None:
            raise RuntimeError(f"service {self.name!r} is not started")
        self._service_keys.declare(robot, started.session, started.admission, guard)

    def undeclare_all(self) -> None:
        """Undeclare every robot's service keys of this service (at shutdown)."""
        self._service_keys.undeclare_all()

    # -- shutdown steps --------------------------------------------------------------------
    def stop_workers(self, workers: BatchWorkers[Job]) -> None:
        """Let admitted requests finish (bounded by INFLIGHT_WAIT_S), then stop the workers."""
        if not workers.shutdown(INFLIGHT_WAIT_S):
            log.warning(
                "%s: %d request(s) still running after %.1f s; closing anyway",
                self.who,
                workers.queue.load,
                INFLIGHT_WAIT_S,
            )
        self.batch_stats.log_summary(self.who)
        if workers.low_runs:
            log.info(
                "%s: %d batch(es) of robots using far more than the others ran at low priority",
                self.who,
                workers.low_runs,
            )
