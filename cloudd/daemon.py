"""The cloud daemon: serves its services to robots, with one standby/service state per robot and
service.

The room, in a request's order: `service_keys` (the robots' keys) -> `admission` -> `batch_queue`
-> `workers` -> `batch_runner` -> `replies`; beside it the control side: `probe`, `control`,
`state` and `robot_book`, `registry_link`; and `plane`/`planes`, which hold all of that once per
service.

Services: a deployment serves every service the fleet file gives it (`FleetConfig.services_of`),
each in a plane of its own (`cloudd.plane.ServicePlane`) built from the service's view of the
fleet (`FleetConfig.for_service`), so each service has its own model (an ONNX split, or a
Python handler whose only cut is 0), robot book and states, service keys, controller, queue and
workers, and its own state per robot: a deployment may serve robot-1's `detect` and stand by
for its `segment`. The daemon keeps one Zenoh session, one liveliness token, one probe key and
one ctl key, whose requests go to the plane of the service they name (`cloudd.planes`: none is
the fleet's first service; a service not served here gets a named `unknown_service` error
reply). A one-service fleet has one plane and behaves as a deployment of one model always did.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. For each service, load its model split from the partition cache (`load_partition`; split on
   first use) and warm one onnxruntime suffix session per cut by running it once
   (`cloudd.suffixes`); a handler's service is opened by calling the handler once.
   Every session shares one copy of the weights (`SplitModel`), so memory stays flat in the
   number of cuts. With `batching.enabled`, each suffix is first given a batch axis and checked
   against one-item runs (`SplitModel.enable_batching`); a cut that cannot take a batch is
   named in the log and runs one request at a time.
2. Open a Zenoh peer session: it connects to the registry's endpoint and listens on the machine's
   own. An unreachable registry does not stop a peer from opening (Zenoh keeps retrying in the
   background, backing off from 1 s to 4 s): the daemon says so, naming the endpoint, and serves
   meanwhile. A client session cannot open without the registry: that is retried with backoff
   until it opens or the daemon is stopped (`cloudd.registry_link`).
3. Start the timer thread (delayed replies, held queries), then each service's workers and their
   queue (`cloudd.batch_queue`: per-robot queues served round robin, an in-flight limit per
   robot, batches of one cut; the workers' replies use the timer, so they stop before it does).
4. Declare `dep/<id>/probe` (answered in every state, `cloudd.probe`) and `dep/<id>/ctl`
   (`cloudd.control`), and follow the registry's membership (`common.membership`): logged when
   it comes and goes.
5. Announce the liveliness token `alive/cloud/<id>`: from now on the registry may use us (it
   probes the deployment for each service it serves: the probe reply is its registration).

Each step hands what it made to the lifecycle (`Daemon.hold`, `on_release`, `announce`), which
releases it all at shutdown in reverse order, the token first, also after a failed startup.

Every robot starts in standby in every service: only a ctl `service(robot, epoch)` from the
registry naming the service declares the robot's anycast key `svc/<service>/<robot>/infer`
(complete=True), and the ack is sent only after the declaration; `standby` undeclares it, then
acks. The epoch rules are in `cloudd.state`.

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
`stop(drain=True)`) drains first: every robot in service, in every service, becomes `draining`,
the registry is asked on `reg/drain` to move them, and once it answers (or after DRAIN_TIMEOUT_S
without an answer) the daemon stops as above, well within 2 s.
"""

from __future__ import annotations

import functools
import logging
import signal
import threading
from collections.abc import Callable

import zenoh

from cloudd.batch_queue import BatchPolicy
from cloudd.batch_stats import BatchStats
from cloudd.control import CtlKey
from cloudd.faults import FaultInjector, describe
from cloudd.limits import CloudLimits
from cloudd.metrics import CloudMetrics
from cloudd.plane import INFLIGHT_WAIT_S, DeploymentParts, ServicePlane
from cloudd.planes import Planes
from cloudd.probe import ProbeResponder
from cloudd.refusals import Refusals
from cloudd.registry_link import DRAIN_TIMEOUT_S, RegistryLink
from cloudd.replies import Replier
from cloudd.state import RobotServiceState
from common import keys
from common.config import FleetConfig, MachineConfig
from common.daemon import Daemon
from common.keys import Role
from common.membership import MembershipView
from common.metrics import MetricsEndpoint, serve
from common.partition.runtime import SplitModel
from common.providers import ProviderCheck
from common.wire import ErrorReply
from common.wire.registry import (
    CAP_CTL,
    CAP_FAULT_INJECTION,
    CAP_INFER,
    CAP_PROBE,
    CtlReply,
    CtlRequest,
    FaultSpec,
    ProbeReply,
)

# The daemon's public names, some defined beside it (the tests read DRAIN_TIMEOUT_S from here).
__all__ = ["CAPABILITIES", "DRAIN_TIMEOUT_S", "INFLIGHT_WAIT_S", "BatchStats", "CloudDaemon"]

log = logging.getLogger(__name__)

CAPABILITIES = (CAP_INFER, CAP_PROBE, CAP_CTL, CAP_FAULT_INJECTION)


class CloudDaemon(Daemon):
    """One deployment of the fleet's services: `CloudDaemon(cfg, "edge-1").run()`.

    `fault` overrides the machine's configured fault injection at start; `drop_seed` seeds the
    drop decisions (tests). `ready` (the lifecycle's) is set once startup is done: the daemon
    serves.
    `limits` are the machine's limits, `refusals` counts what they (and the rest) refused.

    The daemon keeps the lifecycle and wires its parts: `Planes` (one `ServicePlane` per service
    served: model, robot book, service keys, controller, queue, workers), `Replier` (replies,
    delays, held queries), `ProbeResponder` and `CtlKey` (the probe and ctl keys, dispatched to
    the planes) and `RegistryLink` (session, membership, drain). Views without a service name
    (`model`, `states`, `batch_stats`, ...) are the first served service's (a one-service fleet's
    only one); `plane(name)` gives any.
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
        self._replies = Replier(deployment, self.faults, self.throttled)
        self._planes = Planes(
            cfg,
            DeploymentParts(
                deployment=deployment,
                machine=self.machine,
                capabilities=CAPABILITIES,
                faults=self.faults,
                replies=self._replies,
                limits=self.limits,
                refusals=self.refusals,
                throttled=self.throttled,
                closing=self.closing,
            ),
        )
        self._probe = ProbeResponder(
            deployment,
            key=keys.dep_probe(cfg.fleet, deployment),
            profile=self._planes.profile,
            faults=self.faults,
            replies=self._replies,
            limits=self.limits,
            refusals=self.refusals,
            throttled=self.throttled,
        )
        self._ctl = CtlKey(
            deployment,
            key=keys.dep_ctl(cfg.fleet, deployment),
            route=self._planes.control,
            replies=self._replies,
            max_request_bytes=self.limits.request_bytes,
            refusals=self.refusals,
            throttled=self.throttled,
        )
        # Made in startup, released by the lifecycle (the models and workers are the planes').
        self._session: zenoh.Session | None = None
        # `/metrics` (`cloudd.metrics`), when the machine's metrics.port or `metrics_port` is set;
        # served first in startup (before the models load).
        self._metrics_port = metrics_port
        self.metrics_endpoint: MetricsEndpoint | None = None
        self.metrics: CloudMetrics | None = None

    # -- public ----------------------------------------------------------------------------
    @property
    def services(self) -> list[str]:
        """The services this deployment serves, in file order."""
        return self._planes.names

    def plane(self, service: str | None = None) -> ServicePlane:
        """The plane of `service` (None: the first served here); UserError if not served."""
        return self._planes.plane(service)

    @property
    def model(self) -> SplitModel:
        """The first service's loaded model (after startup)."""
        model = self._planes.first.model
        if model is None:
            raise RuntimeError("the model is loaded in startup()")
        return model

    @property
    def providers(self) -> ProviderCheck | None:
        """The providers the first service's suffix sessions got (after startup; `fell_back`
        with `providers_fallback: allow` when they did not get an accelerator asked for)."""
        return self._planes.first.providers

    @property
    def batch_stats(self) -> BatchStats:
        """The first service's batch sizes run so far."""
        return self._planes.first.batch_stats

    def stop(self, drain: bool = False) -> None:
        """Ask the daemon to stop (thread-safe); with `drain`, as on SIGTERM."""
        if drain:
            self._drain_on_exit = True
        super().stop()

    def states(self, service: str | None = None) -> dict[str, RobotServiceState]:
        """Every known robot's state and epoch here, in `service` (None: the first served)."""
        return self.plane(service).states()

    def served(self, service: str | None = None) -> dict[str, int]:
        """Frames computed and answered, per robot, in `service` (None: the first served)."""
        return self.plane(service).book.served()

    def profile(self, echo_bytes: int = 0, service: str | None = None) -> ProbeReply | ErrorReply:
        """What a probe naming `service` (None: the fleet's first) is answered with."""
        return self._planes.profile(service, echo_bytes)

    def control(self, request: CtlRequest) -> CtlReply | ErrorReply:
        """Carry out a control request (what the ctl key does) and return the reply."""
        return self._planes.control(request)

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        self._serve_metrics()
        for plane in self._planes:
            self.hold(plane.open_model(), f"{plane.name} model sessions")
            if not plane.warm(self.should_exit):
                return
        if self.should_exit.is_set():
            return
        session = self._registry.open_session()
        if session is None:
            return  # stopped while waiting for the registry
        self._session = self.hold(session, "zenoh session")
        self._replies.start()
        # Delayed replies go out now; held queries are let go.
        self.on_release(self._replies.stop, what="timer thread")
        policy = BatchPolicy.from_config(self.machine.batching)
        for plane in self._planes:
            metrics = self.metrics.service(plane.name) if self.metrics is not None else None
            workers = plane.start(session, policy, self._guard_query, metrics)
            self.on_release(plane.stop_workers, workers, what=f"{plane.name} workers")
        for key, handler, what in [
            (self._probe.key, self._probe.on_query, "probe queryable"),
            (self._ctl.key, self._ctl.on_query, "ctl queryable"),
        ]:
            self.hold(session.declare_queryable(key, self._guard_query(handler, key)), what)
        # Released before the ctl queryable: a ctl arriving meanwhile is refused (closing).
        for plane in self._planes:
            self.on_release(plane.undeclare_all, what=f"{plane.name} service queryables")
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
            "%s: ready: %s; %s, faults: %s",
            self.deployment,
            "; ".join(plane.describe(policy) for plane in self._planes),
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
        self._planes.close()
        super().shutdown()
        self.refusals.log_summary(self.deployment)
        log.info("%s: stopped", self.deployment)

    # -- startup steps ---------------------------------------------------------------------
    def _serve_metrics(self) -> None:
        endpoint = serve(self, self.machine.metrics, self._metrics_port, who=self.name)
        if endpoint is None:
            return
        self.metrics_endpoint = endpoint
        self.metrics = CloudMetrics(
            endpoint.registry,
            self.deployment,
            services=lambda: [plane.reading() for plane in self._planes],
            providers=self._provider_names,
        )

    def _provider_names(self) -> tuple[str, ...]:
        """The execution providers the suffix sessions run on once loaded (the check's `got`),
        before that the ones the machine asks for, for the metrics."""
        providers = self.providers
        if providers is not None:
            return providers.got
        return tuple(p.ort_name for p in self.machine.providers)

    def _guard_query(
        self, handler: Callable[[zenoh.Query], None], key: str
    ) -> Callable[[zenoh.Query], None]:
        """A query handler on `key` as a guarded callback, answered INTERNAL on an error."""
        on_error = functools.partial(self._replies.internal_error, key)
        return self.guarded(handler, what=f"a query on {key}", on_error=on_error)

    # -- shutdown steps --------------------------------------------------------------------
    def _drain(self) -> None:
        """Mark every robot draining in every service and ask the registry to move them;
        bounded in time."""
        session = self._session
        if session is None:
            return  # stopped before the session was open: nothing to drain
        serving = self._planes.drain_all()
        log.info(
            "%s: draining (serving %s); asking the registry to move them",
            self.deployment,
            ", ".join(serving) or "no robot",
        )
        moved = self._registry.drain(session)
        if moved:
            self.drained.set()
        left = self._planes.serving()
        if left:
            log.warning("%s: still serving %s at exit", self.deployment, ", ".join(left))
