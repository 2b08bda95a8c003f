"""The cloud daemon: serves model suffixes to robots, with one standby/service state per robot.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Load the fleet's model split from the partition cache (`load_partition`; split on first use)
   and warm one onnxruntime suffix session per cut by running it once (`cloudd.suffixes`).
   Every session shares one copy of the weights (`SplitModel`), so memory stays flat in the
   number of cuts. With `batching.enabled`, each suffix is first given a batch axis and checked
   against one-item runs (`SplitModel.enable_batching`); a cut that cannot take a batch is
   named in the log and runs one request at a time.
2. Open a Zenoh peer session: it connects to the registry's endpoint and listens on the machine's
   own. An unreachable registry does not stop a peer from opening (Zenoh keeps retrying in the
   background, backing off from 1 s to 4 s): the daemon says so, naming the endpoint, and serves
   meanwhile. A client session cannot open without the registry: that is retried with backoff
   until it opens or the daemon is stopped (`cloudd.registry_link`).
3. Start the timer thread (delayed replies, held queries), then the workers and their queue
   (`cloudd.batch_queue`: per-robot queues served round robin, an in-flight limit per robot,
   batches of one cut; the workers' replies use the timer, so they stop before it does).
4. Declare `dep/<id>/probe` (answered in every state, `cloudd.probe`) and `dep/<id>/ctl`
   (`cloudd.control`), and follow the registry's membership (`common.membership`): logged when
   it comes and goes.
5. Announce the liveliness token `alive/cloud/<id>`: from now on the registry may use us.

Each step hands what it made to the lifecycle (`Daemon.hold`, `on_release`, `announce`), which
releases it all at shutdown in reverse order, the token first, also after a failed startup.

Every robot starts in standby: only a ctl `service(robot, epoch)` from the registry declares the
robot's anycast key `svc/<service>/<robot>/infer` (complete=True), and the ack is sent only after
the declaration; `standby` undeclares it, then acks. The epoch rules are in `cloudd.state`.

Limits (`cloudd.limits`, the machine's `limits` section): a request payload, a declared tensor
size and a probe echo over the deployment's limit get a `too_large` error reply; a robot past its
in-flight limit gets "busy"; a request whose body names another robot than its key gets
`wrong_robot`. Every refusal is counted by reason (`cloudd.refusals`: `refusals`, the probe
reply's `refused`), and the counts are logged at exit.

Threads: Zenoh runs each queryable's callback on a thread of its own. Callbacks only decode,
check and admit a request (`cloudd.admission`), then return; suffixes run on the workers
(`cloudd.batch_runner`). A request the queue does not admit (every slot taken, or its robot at
its in-flight limit) is answered "busy" at once. A batch is decoded request by request, run
once, and each robot is answered with its own rows. Bad input of any kind gets an error reply
naming the problem and one WARNING line (rate-limited by the daemon's `throttled` log), never a
traceback; the daemon keeps serving. Every callback is `guarded`: an unexpected error is logged
and answered as INTERNAL.

Stopping: SIGINT (or `stop()`) stops at once: the token goes first, then the service keys, then
in-flight requests finish (bounded) and the session is closed explicitly. SIGTERM (or
`stop(drain=True)`) drains first: every robot in service becomes `draining`, the registry is asked
on `reg/drain` to move them, and once it answers (or after DRAIN_TIMEOUT_S without an answer) the
daemon stops as above, well within 2 s.
"""

from __future__ import annotations

import functools
import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from cloudd.admission import Admission, Job
from cloudd.batch_queue import BatchCosts, BatchPolicy, FairQueue
from cloudd.batch_runner import BatchRunner
from cloudd.batch_stats import BatchStats
from cloudd.control import Controller
from cloudd.cpu_lanes import UsageMeter, lanes_supported
from cloudd.faults import FaultInjector, describe
from cloudd.limits import CloudLimits
from cloudd.metrics import CloudMetrics
from cloudd.probe import ProbeResponder
from cloudd.refusals import Refusals
from cloudd.registry_link import DRAIN_TIMEOUT_S, RegistryLink
from cloudd.replies import Replier
from cloudd.robot_book import RobotBook
from cloudd.service_keys import ServiceKeys
from cloudd.state import RobotServiceState
from cloudd.suffixes import open_split_model, warm_suffixes
from cloudd.workers import BatchWorkers
from common import keys
from common.config import FleetConfig, MachineConfig
from common.daemon import Daemon
from common.heap import release_freed_memory
from common.keys import Role
from common.membership import MembershipView
from common.metrics import MetricsEndpoint, serve
from common.partition import TensorSpec
from common.partition.runtime import SplitModel
from common.providers import ProviderCheck
from common.wire.registry import (
    CAP_CTL,
    CAP_FAULT_INJECTION,
    CAP_INFER,
    CAP_PROBE,
    PROTOCOL_VERSION,
    CtlReply,
    CtlRequest,
    FaultSpec,
    ProbeReply,
)

# The daemon's public names, some defined beside it (the tests read DRAIN_TIMEOUT_S from here).
__all__ = ["CAPABILITIES", "DRAIN_TIMEOUT_S", "INFLIGHT_WAIT_S", "BatchStats", "CloudDaemon"]

log = logging.getLogger(__name__)

CAPABILITIES = (CAP_INFER, CAP_PROBE, CAP_CTL, CAP_FAULT_INJECTION)

INFLIGHT_WAIT_S = 0.4
"""How long shutdown lets admitted requests finish before closing the session."""


@dataclass(frozen=True)
class _Started:
    """What startup made that queries, control and draining use."""

    model: SplitModel
    session: zenoh.Session
    queue: FairQueue[Job]
    admission: Admission


class CloudDaemon(Daemon):
    """One deployment of the fleet's service: `CloudDaemon(cfg, "edge-1").run()`.

    `fault` overrides the machine's configured fault injection at start; `drop_seed` seeds the
    drop decisions (tests). `ready` (the lifecycle's) is set once startup is done: the daemon
    serves.
    `limits` are the machine's limits, `refusals` counts what they (and the rest) refused.

    The daemon keeps the lifecycle and wires its parts: `RobotBook` (per-robot state, counters,
    service keys), `ServiceKeys` (declaring them), `Replier` (replies, delays, held queries),
    `Controller` (the ctl key), `ProbeResponder` (the probe key), `Admission` (the service keys'
    callbacks), `BatchRunner` (the workers' runs) and `RegistryLink` (session, membership,
    drain).
    """

    name = "cloud"

    def __init__(
        self,
        cfg: FleetConfig,
        deployment: str,
        *,
        fault: FaultSpec | None = None,
        drop_seed: int | None = None,
        metrics_port: int | None = None,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.deployment = deployment
        self.machine: MachineConfig = cfg.machine(deployment, role=Role.CLOUD)
        self.name = f"cloud {deployment}"
        if fault is None:
            fault = FaultSpec(**self.machine.fault.model_dump())
        self.faults = FaultInjector(fault, seed=drop_seed)
        self.drained = threading.Event()
        self._registry = RegistryLink(cfg, deployment, stop=self.should_exit)
        self.registry_seen = self._registry.seen
        self._drain_on_exit = False

        self.limits = CloudLimits.of(cfg, self.machine)
        self.refusals = Refusals()
        self._book = RobotBook(cfg.robot_ids, closing=self.closing)
        self._service_keys = ServiceKeys(cfg.fleet, cfg.service_name, deployment, self._book)
        self._replies = Replier(deployment, self.faults, self.throttled)
        self._probe = ProbeResponder(
            deployment,
            key=keys.dep_probe(cfg.fleet, deployment),
            profile=self.profile,
            faults=self.faults,
            replies=self._replies,
            limits=self.limits,
            refusals=self.refusals,
            throttled=self.throttled,
        )
        self._controller = Controller(
            deployment,
            key=keys.dep_ctl(cfg.fleet, deployment),
            book=self._book,
            faults=self.faults,
            replies=self._replies,
            declare_service=self._declare_service,
            max_request_bytes=self.limits.request_bytes,
            refusals=self.refusals,
            throttled=self.throttled,
            set_in_flight=self._set_in_flight,
        )
        self._costs = BatchCosts()
        self.batch_stats = BatchStats()
        self.providers: ProviderCheck | None = None
        """The providers the suffix sessions got (after startup; `fell_back` with
        `providers_fallback: allow` when they did not get an accelerator asked for)."""

        # Made in startup, released by the lifecycle: the model as soon as it is loaded (a probe
        # never comes before the session, but startup may stop in between), the rest in one
        # `_Started` once the session and the workers are up.
        self._model: SplitModel | None = None
        self._cut_specs: list[list[TensorSpec]] = []
        self._started: _Started | None = None
        # `/metrics` (`cloudd.metrics`), when the machine's metrics.port or `metrics_port` is set;
        # served first in startup (before the model loads), so not part of `_Started`.
        self._metrics_port = metrics_port
        self.metrics_endpoint: MetricsEndpoint | None = None
        self.metrics: CloudMetrics | None = None

    # -- public ----------------------------------------------------------------------------
    @property
    def model(self) -> SplitModel:
        """The loaded split model (after startup)."""
        if self._model is None:
            raise RuntimeError("the model is loaded in startup()")
        return self._model

    @property
    def _parts(self) -> _Started:
        """The started parts (RuntimeError before startup has opened the session)."""
        if self._started is None:
            raise RuntimeError("the cloud daemon is not started")
        return self._started

    def stop(self, drain: bool = False) -> None:
        """Ask the daemon to stop (thread-safe); with `drain`, as on SIGTERM."""
        if drain:
            self._drain_on_exit = True
        super().stop()

    def states(self) -> dict[str, RobotServiceState]:
        """Every known robot's state and epoch here."""
        return self._book.states()

    def served(self) -> dict[str, int]:
        """Frames computed and answered, per robot."""
        return self._book.served()

    def profile(self, echo_bytes: int = 0) -> ProbeReply:
        """What a probe is answered with."""
        snapshot, served = self._book.snapshot()
        states = {robot: st.state for robot, st in snapshot.items()}
        model = self._model
        queue = self._started.queue if self._started is not None else None
        return ProbeReply(
            deployment=self.deployment,
            protocol_version=PROTOCOL_VERSION,
            capabilities=CAPABILITIES,
            service=self.cfg.service_name,
            model_digest=model.digest if model is not None else "",
            states=states,
            load=queue.load if queue is not None else 0,
            capacity=queue.capacity if queue is not None else 0,
            num_cuts=len(self._cut_specs),
            fault=self.faults.get(),
            echo=bytes(echo_bytes),
            epochs={robot: st.wire_epoch for robot, st in snapshot.items()},
            served=served,
            refused=self.refusals.snapshot(),
            providers=self.providers.got if self.providers is not None else (),
            providers_fallback=self.providers is not None and self.providers.fell_back,
        )

    def control(self, request: CtlRequest) -> CtlReply:
        """Carry out a control request (what the ctl key does) and return the reply."""
        return self._controller.control(request)

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        self._serve_metrics()
        self._load_model()
        if self.should_exit.is_set():
            return
        session = self._registry.open_session()
        if session is None:
            return  # stopped while waiting for the registry
        self.hold(session, "zenoh session")
        self._replies.start()
        # Delayed replies go out now; held queries are let go.
        self.on_release(self._replies.stop, what="timer thread")
        policy = BatchPolicy.from_config(self.machine.batching)
        workers, admission = self._start_workers(policy)
        queue = workers.queue
        self._started = _Started(
            model=self.model, session=session, queue=queue, admission=admission
        )
        for key, handler, what in [
            (self._probe.key, self._probe.on_query, "probe queryable"),
            (self._controller.key, self._controller.on_query, "ctl queryable"),
        ]:
            self.hold(session.declare_queryable(key, self._guard_query(handler, key)), what)
        # Released before the ctl queryable: a ctl arriving meanwhile is refused (closing).
        self.on_release(self._service_keys.undeclare_all, what="service queryables")
        self.hold(
            MembershipView(
                session, self.cfg.fleet, roles=("registry",), on_change=self._registry.on_change
            ),
            "registry membership",
        )
        self.announce(
            session.liveliness().declare_token(
                keys.alive_deployment(self.cfg.fleet, self.deployment)
            )
        )
        log.info(
            "%s: ready: service %r, %d cuts warm, %d workers, %d slots, at most %d per robot, "
            "%s, %s, faults: %s",
            self.deployment,
            self.cfg.service,
            len(self._cut_specs),
            workers.workers,
            queue.capacity,
            policy.max_in_flight_per_robot,
            (
                f"batches of up to {policy.max_batch} within {policy.max_queue_delay_s * 1000:g} ms"
                if self.machine.batching.enabled
                else "batching off"
            ),
            self.limits.describe(),
            describe(self.faults.get()),
        )

    def main_loop(self) -> None:
        self.should_exit.wait()
        if self._drain_on_exit or self.stop_signal == signal.SIGTERM:
            self._drain()

    def shutdown(self) -> None:
        """Refuse new work, then release everything startup made: the token first (the registry
        reroutes at once instead of waiting for a timeout), then in reverse order. Safe twice."""
        self._book.close()
        super().shutdown()
        self.refusals.log_summary(self.deployment)
        log.info("%s: stopped", self.deployment)

    # -- startup steps ---------------------------------------------------------------------
    def _serve_metrics(self) -> None:
        endpoint = serve(self, self.machine.metrics, self._metrics_port, who=self.name)
        if endpoint is None:
            return
        self.metrics_endpoint = endpoint
        queue = self._queue_numbers
        self.metrics = CloudMetrics(
            endpoint.registry,
            self.deployment,
            states=self.states,
            queue=queue,
            providers=self._provider_names,
            model=self._model_names,
        )

    def _provider_names(self) -> tuple[str, ...]:
        """The execution providers the suffix sessions run on once loaded (the check's `got`),
        before that the ones the machine asks for, for the metrics."""
        if self.providers is not None:
            return self.providers.got
        return tuple(p.ort_name for p in self.machine.providers)

    def _model_names(self) -> tuple[str, str]:
        """(the fleet's model, its digest once loaded), for the metrics."""
        model = self._model
        return self.cfg.model_spec, model.digest if model is not None else ""

    def _queue_numbers(self) -> tuple[int, int, int] | None:
        """(requests pending, requests queued, capacity), for the metrics; None before the
        queue exists."""
        started = self._started
        if started is None:
            return None
        queue = started.queue
        return queue.load, queue.queued, queue.capacity

    def _load_model(self) -> None:
        started = time.monotonic()
        log.info("%s: loading %s", self.deployment, self.cfg.model_spec)
        model = open_split_model(self.cfg, self.machine)
        self._model = self.hold(model, "model sessions")
        warm = warm_suffixes(
            model,
            self.machine,
            deployment=self.deployment,
            model_name=self.cfg.model_spec,
            stop=self.should_exit,
        )
        if warm is None:
            return
        # The warm-up's first runs allocate tensor by tensor and glibc keeps what they freed;
        # later runs take one planned block each, so giving it back now is not undone.
        release_freed_memory(self.deployment)
        self._cut_specs = cut_specs = warm.cut_specs
        self.providers = warm.providers
        oversized = self.limits.oversized_tensors(cut_specs)
        if oversized:
            log.warning(
                "%s: %s over limits.max_tensor_bytes (%d bytes): requests for these cuts will "
                "be refused",
                self.deployment,
                ", ".join(oversized),
                self.limits.tensor_bytes,
            )
        log.info(
            "%s: model %s (%s) loaded: %d cuts, %.1f MB of weights, on %s, in %.1f s",
            self.deployment,
            model.partition.model,
            model.digest[:12],
            model.num_cuts,
            model.weight_bytes / 1e6,
            ", ".join(warm.providers.got),
            time.monotonic() - started,
        )

    def _start_workers(self, policy: BatchPolicy) -> tuple[BatchWorkers[Job], Admission]:
        """The queue, the workers running its batches and the service keys' admission."""
        # Each worker may run a whole batch; `queue` slots wait beyond that.
        slots = self.machine.workers * policy.max_batch + self.machine.queue
        queue: FairQueue[Job] = FairQueue(
            policy, slots=slots, costs=self._costs, batchable=self.model.batched
        )
        admission = Admission(
            self.deployment,
            digest=self.model.digest,
            cut_specs=self._cut_specs,
            queue=queue,
            book=self._book,
            faults=self.faults,
            replies=self._replies,
            limits=self.limits,
            refusals=self.refusals,
            throttled=self.throttled,
            metrics=self.metrics,
        )
        runner = BatchRunner(
            self.deployment,
            model=self.model,
            cut_specs=self._cut_specs,
            queue=queue,
            costs=self._costs,
            stats=self.batch_stats,
            book=self._book,
            replies=self._replies,
            closing=self.closing,
            throttled=self.throttled,
            metrics=self.metrics,
        )
        yields = self.machine.batching.heavy_robots_low_priority and lanes_supported()
        workers = BatchWorkers(
            queue,
            runner.run,
            self.machine.workers,
            name=f"{self.deployment}-worker",
            meter=UsageMeter() if yields else None,
        )
        workers.start()
        self.on_release(self._stop_workers, workers, what="workers")
        return workers, admission

    # -- service keys ----------------------------------------------------------------------
    def _set_in_flight(self, robot: str, announced: int) -> int | None:
        """The Controller passes on the frames in flight a robot announced; the limit now in
        force for it (None before the queue exists)."""
        started = self._started
        return None if started is None else started.queue.set_in_flight(robot, announced)

    def _declare_service(self, robot: str) -> None:
        """Declare `robot`'s service keys (`cloudd.service_keys`; the Controller calls this
        before acking service)."""
        self._service_keys.declare(
            robot, self._parts.session, self._parts.admission, self._guard_query
        )

    def _guard_query(
        self, handler: Callable[[zenoh.Query], None], key: str
    ) -> Callable[[zenoh.Query], None]:
        """A query handler on `key` as a guarded callback, answered INTERNAL on an error."""
        on_error = functools.partial(self._replies.internal_error, key)
        return self.guarded(handler, what=f"a query on {key}", on_error=on_error)

    # -- shutdown steps --------------------------------------------------------------------
    def _stop_workers(self, workers: BatchWorkers[Job]) -> None:
        if not workers.shutdown(INFLIGHT_WAIT_S):
            log.warning(
                "%s: %d request(s) still running after %.1f s; closing anyway",
                self.deployment,
                workers.queue.load,
                INFLIGHT_WAIT_S,
            )
        self.batch_stats.log_summary(self.deployment)
        if workers.low_runs:
            log.info(
                "%s: %d batch(es) of robots using far more than the others ran at low priority",
                self.deployment,
                workers.low_runs,
            )

    def _drain(self) -> None:
        """Mark every robot draining and ask the registry to move them; bounded in time."""
        if self._started is None:
            return  # stopped before the session was open: nothing to drain
        session = self._started.session
        serving = self._book.drain_all()
        log.info(
            "%s: draining (serving %s); asking the registry to move them",
            self.deployment,
            ", ".join(serving) or "no robot",
        )
        moved = self._registry.drain(session)
        if moved:
            self.drained.set()
        left = self._book.serving_robots()
        if left:
            log.warning("%s: still serving %s at exit", self.deployment, ", ".join(left))
