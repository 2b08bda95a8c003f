"""The cloud daemon: serves model suffixes to robots, with one standby/service state per robot.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Load the fleet's model split from the partition cache (`load_partition`; split on first use)
   and warm one onnxruntime suffix session per cut by running it once. Every session shares one
   copy of the weights (`SplitModel`), so memory stays flat in the number of cuts. With
   `batching.enabled`, each suffix is first given a batch axis and checked against one-item
   runs (`SplitModel.enable_batching`); a cut that cannot take a batch is named in the log and
   runs one request at a time.
2. Open a Zenoh peer session: it connects to the registry's endpoint and listens on the machine's
   own. An unreachable registry does not stop a peer from opening (Zenoh keeps retrying in the
   background, backing off from 1 s to 4 s): the daemon says so, naming the endpoint, and serves
   meanwhile. A client session cannot open without the registry: that is retried here with
   backoff until it opens or the daemon is stopped.
3. Start the timer thread (delayed replies, held queries), then the workers and their queue
   (`cloudd.batch_queue`: per-robot queues served round robin, an in-flight limit per robot,
   batches of one cut; the workers' replies use the timer, so they stop before it does).
4. Declare `dep/<id>/probe` (answered in every state) and `dep/<id>/ctl`, and follow the
   registry's membership (`common.membership`): logged when it comes and goes.
5. Announce the liveliness token `alive/cloud/<id>`: from now on the registry may use us.

Each step hands what it made to the lifecycle (`Daemon.hold`, `on_release`, `announce`), which
releases it all at shutdown in reverse order, the token first, also after a failed startup.

Every robot starts in standby: only a ctl `service(robot, epoch)` from the registry declares the
robot's anycast key `svc/<service>/<robot>/infer` (complete=True), and the ack is sent only after
the declaration; `standby` undeclares it, then acks. The epoch rules are in `cloudd.state`.

Threads: Zenoh runs each queryable's callback on a thread of its own. Callbacks only decode,
check and admit a request, then return; suffixes run on the workers. A request the queue does not
admit (every slot taken, or its robot at its in-flight limit) is answered "busy" at once. A batch
is decoded request by request, run once, and each robot is answered with its own rows. Bad
input of any kind gets an error reply naming the problem and one WARNING line (rate-limited by
the daemon's `throttled` log), never a traceback; the daemon keeps serving. Every callback is
`guarded`: an unexpected error is logged and answered as INTERNAL.

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
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import zenoh

from cloudd.batch_queue import Batch, BatchCosts, BatchPolicy, FairQueue, Pending, Refusal
from cloudd.faults import FaultInjector, describe
from cloudd.state import RobotState, StateTable, Verdict
from cloudd.validate import check_request, decode_tensors
from cloudd.workers import BatchWorkers, DelayedActions
from common import keys
from common.config import FleetConfig, MachineConfig
from common.daemon import Daemon
from common.errors import UserError
from common.membership import MemberChange, MembershipView
from common.partition import TensorSpec, load_partition, ort_reason
from common.session import open_session, zenoh_error_text, zenoh_settings
from common.split_runtime import SplitModel
from common.wire import ErrorCode, ErrorReply, WireError, decode, error_reply
from common.wire.cloud_to_robot import BusyReply, InferReply
from common.wire.registry import (
    CAP_CTL,
    CAP_FAULT_INJECTION,
    CAP_INFER,
    CAP_PROBE,
    PROTOCOL_VERSION,
    CtlOp,
    CtlReply,
    CtlRequest,
    DeploymentState,
    DrainReply,
    DrainRequest,
    FaultSpec,
    ProbeReply,
    ProbeRequest,
)
from common.wire.robot_to_cloud import InferRequest

log = logging.getLogger(__name__)

CAPABILITIES = (CAP_INFER, CAP_PROBE, CAP_CTL, CAP_FAULT_INJECTION)

DRAIN_TIMEOUT_S = 1.2
"""How long a draining daemon waits for the registry to move its robots before exiting anyway
(the daemon promises to stop within 2 s of SIGTERM)."""

INFLIGHT_WAIT_S = 0.4
"""How long shutdown lets admitted requests finish before closing the session."""

HOLD_UNANSWERED_S = 30.0
"""How long a query left unanswered on purpose (drop, stall) is held before it is let go: longer
than any querier waits, so it sees a timeout, as it would for a lost message or a frozen host."""

OPEN_RETRY_FIRST_S = 0.5
OPEN_RETRY_MAX_S = 8.0
"""Backoff between attempts to open a client session while the registry is unreachable."""


def _payload(query: zenoh.Query) -> bytes:
    payload = query.payload
    return b"" if payload is None else payload.to_bytes()


@dataclass(frozen=True)
class _Job:
    """What answering one admitted inference request needs."""

    key: str
    query: zenoh.Query
    request: InferRequest


class BatchStats:
    """Batches run and requests refused, for the log and the tests (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.sizes: Counter[int] = Counter()
        self.refused: Counter[Refusal] = Counter()

    def ran(self, size: int) -> None:
        with self._lock:
            self.sizes[size] += 1

    def refuse(self, why: Refusal) -> None:
        with self._lock:
            self.refused[why] += 1

    def snapshot(self) -> tuple[dict[int, int], dict[Refusal, int]]:
        with self._lock:
            return dict(self.sizes), dict(self.refused)


class CloudDaemon(Daemon):
    """One deployment of the fleet's service: `CloudDaemon(cfg, "edge-1").run()`.

    `fault` overrides the machine's configured fault injection at start; `drop_seed` seeds the
    drop decisions (tests). `ready` is set once the daemon serves (its token is declared).
    """

    name = "cloud"

    def __init__(
        self,
        cfg: FleetConfig,
        deployment: str,
        *,
        fault: FaultSpec | None = None,
        drop_seed: int | None = None,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.deployment = deployment
        self.machine: MachineConfig = cfg.machine(deployment, role="cloud")
        self.name = f"cloud {deployment}"
        if fault is None:
            fault = FaultSpec(**self.machine.fault.model_dump())
        self.faults = FaultInjector(fault, seed=drop_seed)
        self.ready = threading.Event()
        self.registry_seen = threading.Event()
        self.drained = threading.Event()

        # Guards the states, the counters and the service queryables; `closing` is set under it
        # too, so no service key is declared once shutdown has collected them.
        self._lock = threading.Lock()
        self._states = StateTable(cfg.robot_ids)
        self._served: dict[str, int] = {}
        self._unanswered: set[str] = set()  # robots in service not answered since they entered
        self._service_queryables: dict[str, zenoh.Queryable[None]] = {}
        self._drain_on_exit = False

        # Made in startup (None before), released by the lifecycle.
        self._model: SplitModel | None = None
        self._cut_specs: list[list[TensorSpec]] = []
        self._queue: FairQueue[_Job] | None = None
        self._costs = BatchCosts()
        self.batch_stats = BatchStats()
        self._timer: DelayedActions | None = None
        self._session: zenoh.Session | None = None

        self._probe_key = keys.dep_probe(cfg.fleet, deployment)
        self._ctl_key = keys.dep_ctl(cfg.fleet, deployment)

    # -- public ----------------------------------------------------------------------------
    @property
    def model(self) -> SplitModel:
        """The loaded split model (after startup)."""
        if self._model is None:
            raise RuntimeError("the model is loaded in startup()")
        return self._model

    def stop(self, drain: bool = False) -> None:
        """Ask the daemon to stop (thread-safe); with `drain`, as on SIGTERM."""
        if drain:
            self._drain_on_exit = True
        super().stop()

    def states(self) -> dict[str, RobotState]:
        """Every known robot's state and epoch here."""
        with self._lock:
            return self._states.snapshot()

    def served(self) -> dict[str, int]:
        """Frames computed and answered, per robot."""
        with self._lock:
            return dict(self._served)

    def profile(self, echo_bytes: int = 0) -> ProbeReply:
        """What a probe is answered with."""
        with self._lock:
            snapshot = self._states.snapshot()
            served = dict(self._served)
        states = {robot: st.state for robot, st in snapshot.items()}
        model = self._model
        queue = self._queue
        return ProbeReply(
            deployment=self.deployment,
            protocol_version=PROTOCOL_VERSION,
            capabilities=CAPABILITIES,
            service=self.cfg.service,
            model_digest=model.digest if model is not None else "",
            states=states,
            load=queue.load if queue is not None else 0,
            capacity=queue.capacity if queue is not None else 0,
            num_cuts=len(self._cut_specs),
            fault=self.faults.get(),
            echo=bytes(echo_bytes),
            epochs={robot: st.wire_epoch for robot, st in snapshot.items()},
            served=served,
        )

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        self._load_model()
        if self.should_exit.is_set():
            return
        session = self._open_session()
        if session is None:
            return  # stopped while waiting for the registry
        self._session = self.hold(session, "zenoh session")
        self._timer = timer = DelayedActions(name=f"{self.deployment}-timer")
        timer.start()
        # Delayed replies go out now; held queries are let go.
        self.on_release(timer.flush_and_stop, what="timer thread")
        policy = BatchPolicy.from_config(self.machine.batching)
        # Each worker may run a whole batch; `queue` slots wait beyond that.
        slots = self.machine.workers * policy.max_batch + self.machine.queue
        queue: FairQueue[_Job] = FairQueue(
            policy, slots=slots, costs=self._costs, batchable=self.model.batched
        )
        self._queue = queue
        workers = BatchWorkers(
            queue, self._run_batch, self.machine.workers, name=f"{self.deployment}-worker"
        )
        workers.start()
        self.on_release(self._stop_workers, workers, what="workers")
        for key, handler, what in [
            (self._probe_key, self._on_probe, "probe queryable"),
            (self._ctl_key, self._on_ctl, "ctl queryable"),
        ]:
            on_error = functools.partial(self._internal_error, key)
            callback = self.guarded(handler, what=f"a query on {key}", on_error=on_error)
            self.hold(session.declare_queryable(key, callback), what)
        # Released before the ctl queryable: a ctl arriving meanwhile is refused (closing).
        self.on_release(self._undeclare_services, what="service queryables")
        self.hold(
            MembershipView(
                session, self.cfg.fleet, roles=("registry",), on_change=self._on_registry
            ),
            "registry membership",
        )
        self.announce(
            session.liveliness().declare_token(keys.alive_cloud(self.cfg.fleet, self.deployment))
        )
        self.ready.set()
        log.info(
            "%s: ready: service %r, %d cuts warm, %d workers, %d slots, at most %d per robot, "
            "%s, faults: %s",
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
            describe(self.faults.get()),
        )

    def main_loop(self) -> None:
        self.should_exit.wait()
        if self._drain_on_exit or self.stop_signal == signal.SIGTERM:
            self._drain()

    def shutdown(self) -> None:
        """Refuse new work, then release everything startup made: the token first (the registry
        reroutes at once instead of waiting for a timeout), then in reverse order. Safe twice."""
        self.ready.clear()
        with self._lock:
            self.closing.set()
        super().shutdown()
        log.info("%s: stopped", self.deployment)

    def _undeclare_services(self) -> None:
        with self._lock:
            service = list(self._service_queryables.values())
            self._service_queryables.clear()
        for queryable in service:
            try:
                queryable.undeclare()
            except zenoh.ZError as exc:  # keep undeclaring the others
                log.warning("%s: undeclaring a service key failed: %s", self.deployment, exc)

    def _stop_workers(self, workers: BatchWorkers[_Job]) -> None:
        if not workers.shutdown(INFLIGHT_WAIT_S):
            log.warning(
                "%s: %d request(s) still running after %.1f s; closing anyway",
                self.deployment,
                workers.queue.load,
                INFLIGHT_WAIT_S,
            )
        sizes, refused = self.batch_stats.snapshot()
        if sizes:
            runs = sum(sizes.values())
            frames = sum(size * count for size, count in sizes.items())
            log.info(
                "%s: %d request(s) computed in %d run(s) (mean batch %.2f, largest %d); "
                "refused busy: %s",
                self.deployment,
                frames,
                runs,
                frames / runs,
                max(sizes),
                ", ".join(f"{n} ({why.value})" for why, n in refused.items()) or "none",
            )

    # -- startup steps ---------------------------------------------------------------------
    def _load_model(self) -> None:
        cfg = self.cfg
        shape = tuple(cfg.input_shape) if cfg.input_shape else None
        started = time.monotonic()
        log.info("%s: loading %s", self.deployment, cfg.model)
        partition = load_partition(
            cfg.model, cfg.cuts.names or "auto", cfg.cuts.max_cut_tensors, shape
        )
        model = SplitModel(
            partition,
            providers=self.machine.providers,
            threads=self.machine.threads or None,
            lazy=True,
        )
        self._model = self.hold(model, "model sessions")
        cut_specs = [model.cut_tensor_specs(k) for k in range(model.num_cuts)]
        unbatched: dict[int, str] = {}
        # Build and run every suffix once now: nothing is built on the frame path, and the first
        # frame of each cut costs what later ones do.
        for k, specs in enumerate(cut_specs):
            if self.should_exit.is_set():
                return
            if self.machine.batching.enabled:
                reason = model.enable_batching(k)
                if reason is not None:
                    unbatched[k] = reason
            zeros = {s.name: np.zeros(s.shape, dtype=s.dtype) for s in specs}
            try:
                model.run_suffix(k, zeros)
            except Exception as exc:
                raise UserError(
                    f"{cfg.model}: cannot run the suffix of cut {k} with providers "
                    f"{', '.join(self.machine.providers)}: {ort_reason(exc)}"
                ) from None
        self._cut_specs = cut_specs
        if self.machine.batching.enabled:
            self._log_batching(model.num_cuts, unbatched)
        log.info(
            "%s: model %s (%s) loaded: %d cuts, %.1f MB of weights, in %.1f s",
            self.deployment,
            partition.model,
            model.digest[:12],
            model.num_cuts,
            model.weight_bytes / 1e6,
            time.monotonic() - started,
        )

    def _log_batching(self, num_cuts: int, unbatched: dict[int, str]) -> None:
        """Say which cuts take a batch, and why the others run one request at a time."""
        batched = num_cuts - len(unbatched)
        log.info(
            "%s: batching: %d of %d cuts take a batch of up to %d",
            self.deployment,
            batched,
            num_cuts,
            self.machine.batching.max_batch,
        )
        for k, reason in unbatched.items():
            log.warning(
                "%s: batching: cut %d runs one request at a time: %s", self.deployment, k, reason
            )

    def _open_session(self) -> zenoh.Session | None:
        endpoint = self.cfg.registry.endpoint
        mode = zenoh_settings(self.cfg, machine=self.deployment)["mode"]
        backoff_s = OPEN_RETRY_FIRST_S
        attempt = 0
        while not self.should_exit.is_set():
            attempt += 1
            try:
                session = open_session(self.cfg, machine=self.deployment)
            except UserError as exc:
                if mode != "client":
                    raise  # a peer opens without the registry: this is something else
                log.warning(
                    "%s: cannot reach the registry at %s (attempt %d): %s; retrying in %.1f s",
                    self.deployment,
                    endpoint,
                    attempt,
                    exc,
                    backoff_s,
                )
                if self.should_exit.wait(backoff_s):
                    return None
                backoff_s = min(backoff_s * 2, OPEN_RETRY_MAX_S)
                continue
            if not list(session.info.routers_zid()):
                log.warning(
                    "%s: the registry at %s is not reachable yet; serving probes and ctl "
                    "meanwhile (Zenoh keeps retrying in the background with backoff)",
                    self.deployment,
                    endpoint,
                )
            return session
        return None

    # -- registry --------------------------------------------------------------------------
    def _on_registry(self, change: MemberChange) -> None:
        if change.alive:
            self.registry_seen.set()
            log.info("%s: registry %s is up", self.deployment, change.id)
            return
        if not change.alive_ids:
            self.registry_seen.clear()
        log.warning(
            "%s: registry %s is gone; robots keep their current routes meanwhile",
            self.deployment,
            change.id,
        )

    def _drain(self) -> None:
        """Mark every robot draining and ask the registry to move them; bounded in time."""
        session = self._session
        if session is None:
            return
        with self._lock:
            serving = self._states.drain_all()
        log.info(
            "%s: draining (serving %s); asking the registry to move them",
            self.deployment,
            ", ".join(serving) or "no robot",
        )
        request = DrainRequest(deployment=self.deployment, reason="planned shutdown (SIGTERM)")
        answer: DrainReply | ErrorReply | None = None
        started = time.monotonic()
        try:
            replies = session.get(
                keys.reg_drain(self.cfg.fleet),
                payload=request.to_wire(),
                timeout=DRAIN_TIMEOUT_S,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    message = decode(reply.ok.payload.to_bytes(), expect=(DrainReply, ErrorReply))
                except WireError as exc:
                    log.warning("%s: bad drain reply from the registry: %s", self.deployment, exc)
                    continue
                assert isinstance(message, (DrainReply, ErrorReply))
                answer = message
                break
        except zenoh.ZError as exc:
            log.warning("%s: drain request failed: %s", self.deployment, zenoh_error_text(exc))
        took_ms = (time.monotonic() - started) * 1000
        with self._lock:
            left = self._states.serving_robots()
        if isinstance(answer, DrainReply) and answer.ok:
            log.info(
                "%s: the registry moved %s in %.0f ms",
                self.deployment,
                ", ".join(answer.moved) or "no robot",
                took_ms,
            )
            self.drained.set()
        elif answer is not None:
            reason = answer.reason
            log.warning("%s: the registry could not move every robot: %s", self.deployment, reason)
        else:
            log.warning(
                "%s: no registry answered the drain request (waited %.0f ms, at most %.1f s); "
                "exiting anyway",
                self.deployment,
                took_ms,
                DRAIN_TIMEOUT_S,
            )
        if left:
            log.warning("%s: still serving %s at exit", self.deployment, ", ".join(left))

    # -- callbacks -------------------------------------------------------------------------
    def _internal_error(self, key: str, query: zenoh.Query, exc: Exception) -> None:
        """Answer a query on `key` whose callback failed (`guarded` has logged why)."""
        if isinstance(exc, WireError):
            payload = error_reply(exc)
        else:
            payload = ErrorReply.make(
                ErrorCode.INTERNAL, "internal error; see the daemon log"
            ).to_wire()
        self._send(query, key, payload, 0.0)

    def _send(
        self,
        query: zenoh.Query,
        key: str,
        payload: bytes,
        delay_s: float,
        on_sent: Callable[[], None] | None = None,
    ) -> None:
        """Reply to `query` now or after `delay_s` (fault injection), then finalize it."""

        def send() -> None:
            try:
                query.reply(key, payload)
                if on_sent is not None:
                    on_sent()
            except Exception as exc:  # the querier or the session is gone: nothing to do
                self.throttled.warning("%s: reply on %s not sent: %s", self.deployment, key, exc)
            finally:
                try:
                    query.drop()
                except Exception as exc:
                    log.debug("%s: query already finalized: %s", self.deployment, exc)

        timer = self._timer
        if delay_s > 0 and timer is not None:
            timer.call_later(delay_s, send)
        else:
            send()

    def _hold(self, query: zenoh.Query) -> None:
        """Leave `query` unanswered (drop, stall): the querier sees a timeout."""
        timer = self._timer
        if timer is not None:
            timer.call_later(HOLD_UNANSWERED_S, query.drop)

    def _delay_s(self) -> float:
        return self.faults.get().delay_ms / 1000.0

    # -- probe -----------------------------------------------------------------------------
    def _on_probe(self, query: zenoh.Query) -> None:
        fault = self.faults.get()
        if fault.stall:
            self._hold(query)
            return
        payload = _payload(query)
        echo_bytes = 0
        if payload:  # an empty probe asks for the profile alone
            try:
                request = ProbeRequest.from_wire(payload, max_bytes=self.cfg.max_payload_bytes)
            except WireError as exc:
                self.throttled.warning("%s: bad probe request: %s", self.deployment, exc.reason)
                self._send(query, self._probe_key, error_reply(exc), fault.delay_ms / 1000.0)
                return
            echo_bytes = request.echo_bytes
        reply = self.profile(echo_bytes)
        self._send(query, self._probe_key, reply.to_wire(), fault.delay_ms / 1000.0)

    # -- ctl -------------------------------------------------------------------------------
    def _on_ctl(self, query: zenoh.Query) -> None:
        try:
            request = CtlRequest.from_wire(_payload(query), max_bytes=self.cfg.max_payload_bytes)
        except WireError as exc:
            self.throttled.warning("%s: bad ctl request: %s", self.deployment, exc.reason)
            self._send(query, self._ctl_key, error_reply(exc), 0.0)
            return
        reply = self.control(request)
        self._send(query, self._ctl_key, reply.to_wire(), 0.0)

    def control(self, request: CtlRequest) -> CtlReply:
        """Carry out a control request (what the ctl key does) and return the reply."""
        sender = f" from {request.sender}" if request.sender else ""
        if request.op is CtlOp.FAULT:
            assert request.fault is not None  # checked by CtlRequest
            self.faults.set(request.fault)
            log.info("%s: fault injection%s: %s", self.deployment, sender, describe(request.fault))
            return CtlReply(ok=True, deployment=self.deployment, op=request.op)
        if request.op is CtlOp.DRAIN:
            return self._ctl_drain(request, sender)
        assert request.robot is not None  # checked by CtlRequest for service and standby
        return self._ctl_state(request, request.robot, sender)

    def _ctl_drain(self, request: CtlRequest, sender: str) -> CtlReply:
        with self._lock:
            if request.robot is None:
                moved = self._states.drain_all()
                state = DeploymentState.DRAINING
                epoch = 0
            else:
                st = self._states.drain_robot(request.robot)
                moved = [request.robot] if st.serving else []
                state, epoch = st.state, st.wire_epoch
        log.info(
            "%s: drain%s of %s: draining %s",
            self.deployment,
            sender,
            request.robot or "the deployment",
            ", ".join(moved) or "no robot",
        )
        return CtlReply(
            ok=True,
            deployment=self.deployment,
            op=request.op,
            robot=request.robot,
            epoch=epoch,
            state=state,
        )

    def _ctl_state(self, request: CtlRequest, robot: str, sender: str) -> CtlReply:
        queryable: zenoh.Queryable[None] | None = None
        with self._lock:
            if self.closing.is_set():
                current = self._states.get(robot)
                return self._ctl_reply(
                    request, Verdict(False, robot, current, current, "this deployment is stopping")
                )
            if request.op is CtlOp.SERVICE:
                verdict = self._states.decide_service(robot, request.epoch)
            else:
                verdict = self._states.decide_standby(robot, request.epoch)
            self._states.apply(verdict)
            if verdict.undeclare:
                queryable = self._service_queryables.pop(robot, None)
            if verdict.declare:
                self._unanswered.add(robot)
        if verdict.declare:
            try:
                self._declare_service(robot)
            except Exception as exc:
                with self._lock:
                    self._states.restore(verdict)
                reason = f"cannot declare the service key of {robot}: {zenoh_error_text(exc)}"
                log.warning("%s: %s", self.deployment, reason)
                return self._ctl_reply(
                    request, Verdict(False, robot, verdict.before, verdict.before, reason)
                )
        if queryable is not None:
            queryable.undeclare()  # before the ack: the registry relies on it being gone
        if verdict.ok:
            log.info(
                "%s: %s %s at epoch %d%s",
                self.deployment,
                robot,
                verdict.after.state.value,
                verdict.after.epoch,
                sender,
            )
        else:
            log.warning(
                "%s: refused %s(%s, epoch %d)%s: %s",
                self.deployment,
                request.op.value,
                robot,
                request.epoch,
                sender,
                verdict.reason,
            )
        return self._ctl_reply(request, verdict)

    def _ctl_reply(self, request: CtlRequest, verdict: Verdict) -> CtlReply:
        return CtlReply(
            ok=verdict.ok,
            deployment=self.deployment,
            op=request.op,
            robot=verdict.robot,
            epoch=verdict.after.wire_epoch,
            state=verdict.after.state,
            reason=verdict.reason,
        )

    def _declare_service(self, robot: str) -> None:
        session = self._session
        if session is None:
            raise RuntimeError("no session")
        key = keys.svc_infer(self.cfg.fleet, self.cfg.service, robot)
        handler = self.guarded(
            functools.partial(self._on_infer, robot, key),
            what=f"a query on {key}",
            on_error=functools.partial(self._internal_error, key),
        )
        queryable = session.declare_queryable(key, handler, complete=True)
        with self._lock:
            old = self._service_queryables.pop(robot, None)
            self._service_queryables[robot] = queryable
        if old is not None:
            old.undeclare()

    # -- inference -------------------------------------------------------------------------
    def _on_infer(self, robot: str, key: str, query: zenoh.Query) -> None:
        arrived = time.monotonic()
        fault = self.faults.get()
        if fault.stall:
            self._hold(query)
            return
        delay_s = fault.delay_ms / 1000.0
        try:
            request = InferRequest.from_wire(_payload(query), max_bytes=self.cfg.max_payload_bytes)
        except WireError as exc:
            self.throttled.warning(
                "%s: bad inference request for %s: %s", self.deployment, robot, exc.reason
            )
            self._send(query, key, error_reply(exc), delay_s)
            return
        if self.faults.drop_now(fault):
            self._hold(query)
            return
        error = check_request(
            request, robot=robot, digest=self.model.digest, cut_specs=self._cut_specs
        )
        if error is not None:
            self.throttled.warning(
                "%s: refused frame %d of %s: %s",
                self.deployment,
                request.frame,
                robot,
                error.reason,
            )
            self._send(query, key, error.to_wire(), delay_s)
            return
        with self._lock:
            serving = self._states.get(robot).serving and not self.closing.is_set()
        if not serving:
            # A request that crossed a switch: the robot finishes the frame itself.
            log.info("%s: frame %d of %s arrived in standby", self.deployment, request.frame, robot)
            reply = ErrorReply.make(
                ErrorCode.NOT_SERVING, f"{self.deployment} does not serve {robot} now"
            )
            self._send(query, key, reply.to_wire(), delay_s)
            return
        queue = self._queue
        item = Pending(
            robot=robot,
            group=request.cut,
            arrived=arrived,
            deadline_at=arrived + request.deadline_s,
            payload=_Job(key, query, request),
        )
        refusal = queue.offer(item) if queue is not None else Refusal.CLOSED
        if refusal is not None:
            self.batch_stats.refuse(refusal)
            busy = BusyReply(
                frame=request.frame,
                deployment=self.deployment,
                queued=queue.load if queue is not None else 0,
                capacity=queue.capacity if queue is not None else 0,
            )
            self._send(query, key, busy.to_wire(), delay_s)

    def _run_batch(self, batch: Batch[_Job]) -> None:
        """Worker: answer the expired requests, then run the batch's requests together (one
        cut) and answer each with its own results."""
        for item in batch.expired:
            # The robot has finished this frame itself by now: computing it helps nobody.
            request = item.payload.request
            waited_s = batch.taken_at - item.arrived
            self._answer_error(
                item,
                ErrorReply.make(
                    ErrorCode.DEADLINE_EXPIRED,
                    f"frame {request.frame} cannot be answered within its deadline of "
                    f"{request.deadline_s * 1000:.0f} ms (it waited {waited_s * 1000:.0f} ms for "
                    "a worker)",
                ),
            )
        if not batch.items:
            return
        started = time.monotonic()
        if self.closing.is_set():
            stopping = ErrorReply.make(ErrorCode.NOT_SERVING, f"{self.deployment} is stopping")
            for item in batch.items:
                self._answer_error(item, stopping)
            return
        ready: list[tuple[Pending[_Job], dict[str, np.ndarray]]] = []
        for item in batch.items:
            request = item.payload.request
            try:
                # Decoding runs here, on a worker, not on Zenoh's callback thread.
                ready.append((item, decode_tensors(request, self._cut_specs[request.cut])))
            except WireError as exc:
                self.throttled.warning(
                    "%s: frame %d of %s: %s", self.deployment, request.frame, item.robot, exc.reason
                )
                self._release(item)
                self._send(item.payload.query, item.payload.key, error_reply(exc), self._delay_s())
        if not ready:
            return
        try:
            outputs = self.model.run_suffix_batch(batch.group, [tensors for _, tensors in ready])
        except Exception as exc:
            reason = f"suffix of cut {batch.group} failed: {ort_reason(exc)}"
            log.warning(
                "%s: a batch of %d (%s): %s",
                self.deployment,
                len(ready),
                ", ".join(f"{i.robot} frame {i.payload.request.frame}" for i, _ in ready),
                reason,
            )
            for item, _ in ready:
                self._answer_error(item, ErrorReply.make(ErrorCode.INTERNAL, reason))
            return
        compute_s = time.monotonic() - started
        self._costs.record(batch.group, len(ready), compute_s)
        self.batch_stats.ran(len(ready))
        for (item, _), result in zip(ready, outputs, strict=True):
            self._answer(item, result, queue_s=started - item.arrived, compute_s=compute_s)

    def _answer(
        self,
        item: Pending[_Job],
        outputs: dict[str, np.ndarray],
        *,
        queue_s: float,
        compute_s: float,
    ) -> None:
        job, robot = item.payload, item.robot
        with self._lock:
            epoch = self._states.get(robot).wire_epoch
        self._release(item)
        reply = InferReply(
            frame=job.request.frame,
            deployment=self.deployment,
            epoch=epoch,
            outputs=outputs,
            queue_s=queue_s,
            compute_s=compute_s,
        )
        self._send(
            job.query,
            job.key,
            reply.to_wire(),
            self._delay_s(),
            on_sent=functools.partial(self._count_served, robot, job.request.frame, epoch),
        )

    def _answer_error(self, item: Pending[_Job], error: ErrorReply) -> None:
        self._release(item)
        self._send(item.payload.query, item.payload.key, error.to_wire(), self._delay_s())

    def _release(self, item: Pending[_Job]) -> None:
        """Free the request's slot before its reply goes out (`FairQueue.release`)."""
        queue = self._queue
        if queue is not None:
            queue.release(item)

    def _count_served(self, robot: str, frame: int, epoch: int) -> None:
        with self._lock:
            self._served[robot] = self._served.get(robot, 0) + 1
            first = robot in self._unanswered
            self._unanswered.discard(robot)
        if first:
            # One line per stay in service: shows that requests reach this deployment and that
            # its replies go out (a robot that times out against it is then a network problem).
            log.info(
                "%s: first frame of %s answered at epoch %d (frame %d)",
                self.deployment,
                robot,
                epoch,
                frame,
            )
