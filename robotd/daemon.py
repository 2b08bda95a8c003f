"""The robot daemon (`elasticfog robot`): the per-frame split loop, over Zenoh.

Lifecycle (`common.daemon.Daemon`): `startup` loads the split model (one set of shared-weight
onnxruntime sessions, every cut warmed up), builds the policy from a robot-side profile, opens the
frame source and a Zenoh *peer* session connected to the registry endpoint only (the robot's
config names no cloud host: it finds deployments through the registry's router and queries its
anycast service key), declares its publishers and subscribers, then its liveliness token, and
starts the prober and the registry watcher. `main_loop` runs frames until `--frames` or a signal;
`shutdown` undeclares the token first and releases everything in reverse order, closing the
session explicitly (a session still holding callbacks at exit hangs the process).

A frame (DESIGN.md, "A frame's life"): grab → entropy → `policy.decide` → prefix (or the whole
model for P) → encoded `InferRequest` → (emulated uplink) → `get` on the service key with the
deadline → reply, or the robot runs the suffix itself with the reason (`robotd.offload`) →
`policy.observe` → telemetry (JSONL file, `tele/<robot>`, run summary). No frame is ever lost.
A hedged decision also runs the local suffix speculatively (at once, or deferred by the policy
while the reply is expected first) on a thread of the lowest CPU priority
(`robotd.offload.LocalRunner`), so that on a robot short of CPU it does not slow the offload it
hedges, and serves whichever result is ready first. A cloud reply
first cancels the local run; when the robot's result wins, the frame is served and the loop moves
on while the cloud's reply (at most one such frame in flight) is awaited up to its deadline, to
feed the learner; meanwhile the next frames' model runs go to the low-priority thread too.

Registry: the robot watches the registry's liveliness token. When none is up it says so, naming
the endpoint, and keeps saying so with a growing interval (Zenoh keeps reconnecting meanwhile);
frames are computed locally until a deployment serves the robot. When the registry goes away the
robot keeps its route: queries go peer to peer. When it (re)appears the robot registers
(`reg/register`) and follows `route/<robot>`. After `REROUTE_AFTER_FAILURES` consecutive
timeouts or missing routes it also asks the registry for a new route (`reg/reroute`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from common import keys
from common.codec_profile import fidelity_of
from common.config import FleetConfig
from common.daemon import Daemon
from common.errors import UserError
from common.image_input import InputAdapter
from common.partition import load_partition, sample_feeds
from common.profiler import median_ms
from common.session import open_session
from common.split_runtime import SplitModel
from common.wire import WireError, decode
from common.wire.registry import (
    CAP_LOCAL_FALLBACK,
    CAP_PROBE_REPORTS,
    CAP_TELEMETRY,
    PROTOCOL_VERSION,
    RegisterReply,
    RegisterRequest,
    RerouteRequest,
    RouteChange,
)
from common.wire.robot_to_cloud import InferRequest
from common.wire.telemetry import ProbeReport, TelemetryRecord, action_label
from common.wire.tensor_codecs import EncodedTensor, encode_tensor_as
from robotd.calibration import calibration_frames, codec_table, required_codecs
from robotd.entropy import frame_entropy
from robotd.offload import (
    FINISH_GRACE_S,
    REASON_DECODE_ERROR,
    REASON_NO_ROUTE,
    REASON_TIMEOUT,
    STOP_POLL_S,
    CallResult,
    CloudCall,
    LocalRunner,
)
from robotd.pacing import FramePacer, TokenBucket
from robotd.policies import (
    PURE_ROBOT,
    Decision,
    FrameContext,
    Objective,
    Outcome,
    Policy,
    make_policy,
)
from robotd.probes import PROBE_INTERVAL_S, CloudTime, Prober, probe_padding_bytes
from robotd.sources import FrameSource, open_source
from robotd.telemetry import (
    SERVED_BY_CLOUD,
    SERVED_BY_ROBOT,
    RunSummary,
    TelemetryFile,
    jsonl_object,
)

log = logging.getLogger("robotd")

# How long startup waits for the registry's token, then for a deployment serving the robot, so
# the first frames are not finished locally only because the session was still meeting peers.
REGISTRY_WAIT_S = 2.0
ROUTE_WAIT_S = 3.0
# "Registry unreachable" is repeated with this backoff while frames are computed locally.
REGISTRY_RETRY_INITIAL_S = 1.0
REGISTRY_RETRY_MAX_S = 30.0
REGISTER_TIMEOUT_S = 1.0
# Ask the registry for a new route after this many consecutive timeouts / missing routes, at most
# once per REROUTE_MIN_INTERVAL_S.
REROUTE_AFTER_FAILURES = 3
REROUTE_MIN_INTERVAL_S = 1.0
REROUTE_TIMEOUT_S = 1.0
# Whole-model runs timed at startup for the robot-side profile (after the profiler's warm-up).
PROFILE_RUNS = 3
# Minimum whole-model time in a profile (the policies need a positive one).
MIN_PROFILE_MS = 1e-3
# A failure of the same reason is logged again after this many frames of it.
LOG_FAILURE_EVERY = 100
THREAD_JOIN_S = 1.0
# Background waits look at the stop flag this often (shutdown must finish within 2 s).
WAIT_SLICE_S = 0.1
ROBOT_CAPABILITIES = (CAP_LOCAL_FALLBACK, CAP_TELEMETRY, CAP_PROBE_REPORTS)
FAILOVER_REASONS = frozenset({REASON_TIMEOUT, REASON_NO_ROUTE})
_TOKEN = "liveliness token"


@dataclass
class RobotOptions:
    """Run options of the robot daemon; None takes the machine's value from fleet.yaml."""

    source: str | None = None
    frames: int | None = None
    fps: float | None = None
    policy: str | None = None
    telemetry: Path | None = None
    uplink_mbit: float | None = None
    seed: int = 0
    probe_interval_s: float = PROBE_INTERVAL_S
    probe_padding_bytes: int | None = None
    registry_wait_s: float = REGISTRY_WAIT_S
    route_wait_s: float = ROUTE_WAIT_S

    def check(self) -> None:
        """UserError naming the first bad option."""
        if self.frames is not None and self.frames < 1:
            raise UserError(f"--frames must be at least 1, got {self.frames}")
        if self.fps is not None and not (self.fps > 0 and np.isfinite(self.fps)):
            raise UserError(f"--fps must be a positive number, got {self.fps}")
        if self.uplink_mbit is not None and not (
            self.uplink_mbit > 0 and np.isfinite(self.uplink_mbit)
        ):
            raise UserError(f"--uplink-mbit must be a positive number, got {self.uplink_mbit}")
        if self.probe_interval_s <= 0:
            raise UserError(f"probe interval must be > 0 s, got {self.probe_interval_s}")


@dataclass(frozen=True)
class FrameResult:
    """A completed frame, handed to `on_result`: its input, its outputs (whichever path served
    it) and its telemetry record."""

    frame: int
    feeds: dict[str, np.ndarray]
    outputs: dict[str, np.ndarray]
    record: TelemetryRecord
    served_by: str
    hedged: bool


@dataclass
class _Route:
    deployment: str | None = None
    epoch: int = 0
    known: bool = False


@dataclass
class _Frame:
    """One frame on its way through the loop."""

    n: int
    decision: Decision
    entropy: float
    feeds: dict[str, np.ndarray]
    started: float
    cpu_started: float
    epoch: int
    prefix_s: float = 0.0
    local_s: float | None = None
    bytes_up: int = 0
    call: CloudCall | None = None
    result: CallResult | None = None
    outputs: dict[str, np.ndarray] = field(default_factory=dict)
    served_by: str = SERVED_BY_ROBOT
    latency_s: float = 0.0
    cpu_s: float = 0.0


def robot_profile(
    model: SplitModel,
    feeds: dict[str, np.ndarray],
    runs: int = PROFILE_RUNS,
    codecs: Mapping[int, list[dict[str, Any]]] | None = None,
) -> dict[str, Any]:
    """The policies' profile of this robot, cheap enough for every start: the whole model's
    median time measured here, split between each cut's prefix and suffix by their FLOPs (the
    policies then learn the robot's real speed online). A cut without FLOP counts is split by
    its position. `codecs` (`robotd.calibration.codec_table`) gives each cut its measured
    codec entries; those marked `action` become the policy's (cut, codec) actions."""
    full_ms = max(median_ms(lambda: model.run_full(feeds), runs), MIN_PROFILE_MS)
    cuts = model.partition.cuts
    rows = []
    for k, cut in enumerate(cuts):
        total = cut.prefix_flops + cut.suffix_flops
        share = cut.prefix_flops / total if total > 0 else k / max(1, len(cuts))
        row: dict[str, Any] = {
            "index": cut.index,
            "bytes": max(1, cut.bytes),
            "prefix_ms": full_ms * share,
            "suffix_ms": full_ms * (1.0 - share),
        }
        if codecs is not None and cut.index in codecs:
            row["codecs"] = [e for e in codecs[cut.index] if e.get("action")]
        rows.append(row)
    return {"digest": model.digest, "full_ms": full_ms, "cuts": rows}


class RobotDaemon(Daemon):
    """`elasticfog robot`. `policy` and `on_result` let tests replace the policy and see each
    frame's outputs; `__init__` does no I/O."""

    name = "robot"

    def __init__(
        self,
        config: FleetConfig,
        robot_id: str,
        options: RobotOptions | None = None,
        *,
        policy: Policy | None = None,
        on_result: Callable[[FrameResult], None] | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.machine = config.machine(robot_id, role="robot")
        self.robot = robot_id
        self.options = options or RobotOptions()
        self.options.check()
        self.fleet = config.fleet
        self.deadline_s = config.deadline_s
        self.source_spec = self.options.source or self.machine.source
        self.fps = self.options.fps if self.options.fps is not None else self.machine.fps
        uplink = self.options.uplink_mbit
        self.uplink_mbit = uplink if uplink is not None else self.machine.uplink_mbit
        self.policy_spec = self.options.policy or config.policy.kind
        self.name = f"robot {robot_id}"
        self.summary = RunSummary(robot_id)
        self.frames_done = 0
        self._policy_override = policy
        self._on_result = on_result
        self._objective = Objective.parse(config.objective.model_dump())
        self._svc_key = keys.svc_infer(self.fleet, config.service, robot_id)
        self._cleanups: list[tuple[str, Callable[[], None]]] = []
        self._threads_stop = threading.Event()
        self._route = _Route()
        self._route_lock = threading.Lock()
        self._registries: set[str] = set()
        self._clouds: set[str] = set()
        self._members_lock = threading.Lock()
        self._registry_up = threading.Event()
        self._registry_down = threading.Event()
        self._registry_down.set()
        self._served = threading.Event()
        self._cloud_time = CloudTime()
        self._pending: _Frame | None = None
        self._failure_reason: str | None = None
        self._failure_streak = 0
        self._last_reroute = -float("inf")
        # Set in startup.
        self.model: SplitModel
        self.policy: Policy
        self._adapter: InputAdapter
        self._source: FrameSource
        self._session: zenoh.Session
        self._tele_pub: zenoh.Publisher
        self._probe_pub: zenoh.Publisher
        self._telemetry: TelemetryFile | None = None
        self._uplink: TokenBucket | None = None
        self._prober: Prober | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._position: dict[int, int] = {}
        self._local: LocalRunner | None = None

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        try:
            self._startup()
        except BaseException:
            self.shutdown()
            raise

    def _startup(self) -> None:
        cfg = self.config
        shape = tuple(cfg.input_shape) if cfg.input_shape else None
        partition = load_partition(
            cfg.model, cfg.cuts.names or "auto", cfg.cuts.max_cut_tensors, shape
        )
        threads = self.machine.threads or None
        self.model = SplitModel(partition, providers=self.machine.providers, threads=threads)
        specs = self.model.input_specs()
        if len(specs) != 1:
            names = ", ".join(s.name for s in specs)
            raise UserError(
                f"the robot feeds one camera frame; model {cfg.model} has inputs {names}"
            )
        self._input_name = specs[0].name
        self._adapter = InputAdapter(specs[0])
        self._position = {cut.index: k for k, cut in enumerate(partition.cuts)}
        feeds = sample_feeds(specs)
        self._warm_up(feeds)
        self._local = LocalRunner(f"local-run-{self.robot}")
        self._local.start()
        self._cleanups.append(("local-run thread", self._local.stop))
        self.policy = self._policy_override or self._make_policy(self._profile(feeds))
        self._source = open_source(
            self.source_spec,
            height=self._adapter.height,
            width=self._adapter.width,
            seed=self.options.seed,
        )
        self._cleanups.append(("frame source", self._source.close))
        if self.options.telemetry is not None:
            self._telemetry = TelemetryFile(self.options.telemetry)
            self._cleanups.append(("telemetry file", self._telemetry.close))
        if self.uplink_mbit is not None:
            self._uplink = TokenBucket.from_mbit(self.uplink_mbit)
        self._open_zenoh()
        log.info(
            "%s: model %s (%d cuts, digest %s), policy %s, source %s, deadline %.3f s, "
            "registry %s%s",
            self.robot,
            cfg.model,
            self.model.num_cuts,
            self.model.digest[:12],
            self.policy.name,
            self._source.description,
            self.deadline_s,
            cfg.registry.endpoint,
            f", uplink paced to {self.uplink_mbit:g} Mbit/s (emulation)" if self._uplink else "",
        )
        self._wait_for_fleet()

    def _warm_up(self, feeds: dict[str, np.ndarray]) -> None:
        """Run every prefix and suffix once: the first run of an onnxruntime session allocates,
        and that cost belongs to startup, not to the first frames."""
        for k in range(self.model.num_cuts):
            sent = self.model.run_prefix(k, feeds)
            self.model.run_suffix(k, sent, feeds)

    def _profile(self, feeds: dict[str, np.ndarray]) -> dict[str, Any]:
        """This robot's profile, with the (cut, codec) actions measured on its own source."""
        cfg = self.config
        fidelity = cfg.fidelity
        lowest = min(cut.index for cut in self.model.partition.cuts)
        codecs = codec_table(
            self.model,
            lambda: calibration_frames(
                self.source_spec, self._adapter, fidelity.calibration_frames, self.options.seed
            ),
            fidelity_of(fidelity),
            required_codecs(self.policy_spec, lowest),
            {
                "source": self.source_spec,
                "frames": fidelity.calibration_frames,
                "seed": self.options.seed,
                "threads": self.machine.threads,
            },
        )
        return robot_profile(self.model, feeds, codecs=codecs)

    def _make_policy(self, profile: dict[str, Any]) -> Policy:
        spec = self.policy_spec.strip()
        if spec.lower() == "oracle":
            raise UserError(
                "policy oracle needs the true costs, which only the simulator has "
                "(use it with `elasticfog sim`)"
            )
        same = spec.lower() == self.config.policy.kind.strip().lower()
        params = self.config.policy.params if same else {}
        return make_policy(spec, profile, params, self._objective)

    def _open_zenoh(self) -> None:
        cfg = self.config
        session = open_session(cfg, machine=self.robot)
        self._session = session
        self._cleanups.append(("zenoh session", session.close))
        self._tele_pub = session.declare_publisher(keys.tele(self.fleet, self.robot))
        self._cleanups.append(("telemetry publisher", self._tele_pub.undeclare))
        self._probe_pub = session.declare_publisher(keys.tele_probe(self.fleet, self.robot))
        self._cleanups.append(("probe publisher", self._probe_pub.undeclare))
        route_sub = session.declare_subscriber(keys.route(self.fleet, self.robot), self._on_route)
        self._cleanups.append(("route subscriber", route_sub.undeclare))
        liveliness = session.liveliness()
        registry_sub = liveliness.declare_subscriber(
            keys.alive_registries(self.fleet), self._on_registry_token, history=True
        )
        self._cleanups.append(("registry token subscriber", registry_sub.undeclare))
        clouds_sub = liveliness.declare_subscriber(
            keys.alive_clouds(self.fleet), self._on_cloud_token, history=True
        )
        self._cleanups.append(("cloud token subscriber", clouds_sub.undeclare))
        # A querier on the service key only to be told when a deployment serves it (frames use
        # session.get: each has its own timeout).
        querier = session.declare_querier(self._svc_key)
        self._cleanups.append(("service querier", querier.undeclare))
        matching = querier.declare_matching_listener(self._on_matching)
        self._cleanups.append(("service matching listener", matching.undeclare))
        status: Any = querier.matching_status  # a MatchingStatus (the stub says bool)
        if bool(getattr(status, "matching", status)):
            self._served.set()

        padding = self.options.probe_padding_bytes
        if padding is None:
            padding = probe_padding_bytes([c.bytes for c in self.model.partition.cuts])
        self._prober = Prober(
            session,
            self.fleet,
            self.robot,
            max_padding_bytes=padding,
            publish=self._publish_probe,
            alive_clouds=self._alive_clouds,
            cloud_time=self._cloud_time,
            interval_s=self.options.probe_interval_s,
            max_reply_bytes=cfg.max_payload_bytes,
        )
        self._prober.start()
        self._cleanups.append(("prober", self._prober.stop))
        # Ready: announce the robot last, and take the token down first at shutdown.
        # Held on the daemon: a token that is garbage-collected is undeclared.
        self._token = liveliness.declare_token(keys.alive_robot(self.fleet, self.robot))
        self._cleanups.append((_TOKEN, self._token.undeclare))

    def _wait_for_fleet(self) -> None:
        """Give the session a moment to meet the registry and the deployment serving this robot
        (bounded, and cut short by a signal; frames are finished locally meanwhile anyway), then
        leave the registry to the watcher thread."""
        reachable = self._wait_for(
            self._registry_up, self.options.registry_wait_s, self.should_exit
        )
        if not reachable:
            self._report_unreachable("", REGISTRY_RETRY_INITIAL_S)
        watcher = threading.Thread(
            target=self._watch_registry,
            args=(not reachable,),
            name=f"registry-watch-{self.robot}",
            daemon=True,
        )
        watcher.start()
        self._cleanups.append(("registry watcher", lambda: watcher.join(THREAD_JOIN_S)))
        if reachable and not self._wait_for(
            self._served, self.options.route_wait_s, self.should_exit
        ):
            log.info(
                "%s: no deployment serves %s yet; frames are finished on the robot until one does",
                self.robot,
                self._svc_key,
            )

    def shutdown(self) -> None:
        self._threads_stop.set()
        if self._pending is not None and self._pending.call is not None:
            self._pending.call.cancel()
        # The liveliness token goes first (the fleet stops counting on this robot), then the
        # rest in reverse order of startup.
        ordered = [c for c in self._cleanups if c[0] == _TOKEN] + [
            c for c in reversed(self._cleanups) if c[0] != _TOKEN
        ]
        self._cleanups.clear()
        for what, cleanup in ordered:
            try:
                cleanup()
            except Exception as exc:  # keep releasing the rest
                log.warning("%s: releasing the %s failed: %s", self.robot, what, exc)

    # -- the frame loop --------------------------------------------------------------------
    def main_loop(self) -> None:
        pacer = FramePacer(self.fps)
        limit = self.options.frames
        self.summary.started_at = time.perf_counter()
        n = 0
        # Bounded by --frames, or by the stop flag (signals) otherwise.
        while limit is None or n < limit:
            if not pacer.wait(self.should_exit):
                break
            self._settle_pending(block=False)
            frame = self._source.read()
            self.run_frame(n, frame)
            n += 1
        self._settle_pending(block=True)
        self.summary.ended_at = time.perf_counter()
        if self.should_exit.is_set() and limit is not None and n < limit:
            log.info("%s: stopped after %d of %d frames", self.robot, n, limit)

    def run_frame(self, n: int, frame: np.ndarray) -> None:
        """Run one frame to completion (or, hedged with the robot's result first, to the point
        where it is served; its cloud reply is settled later)."""
        started = time.perf_counter()
        cpu_started = time.process_time()
        feeds = {self._input_name: self._adapter(frame)}
        entropy = frame_entropy(frame)
        decision = self.policy.decide(FrameContext(index=n, entropy=entropy))
        with self._route_lock:
            epoch = self._route.epoch
        f = _Frame(n, decision, entropy, feeds, started, cpu_started, epoch)
        model = self.model
        if decision.action == PURE_ROBOT:
            f.outputs = self._compute(lambda options: model.run_full(feeds, run_options=options))
            f.prefix_s = f.latency_s = time.perf_counter() - started
            f.cpu_s = time.process_time() - cpu_started
            self._emit(f)
            return
        k = self._position_of(decision)
        cut = self.model.partition.cuts[k]
        t = time.perf_counter()
        sent = self._compute(lambda options: model.run_prefix(k, feeds, run_options=options))
        # Encoding is the robot's part of the action: it counts in its prefix time.
        encoded = {name: encode_tensor_as(a, decision.codec) for name, a in sent.items()}
        f.prefix_s = time.perf_counter() - t
        f.call = call = self._send(n, cut.index, encoded, epoch, background=decision.hedge)
        f.bytes_up = call.bytes_up
        if decision.hedge:
            self._hedged(f, k, sent)
            return
        finished = call.wait(self.should_exit)
        f.result = self._checked(call.result(stopped=not finished))
        if f.result.reply is not None:
            f.outputs = dict(f.result.reply.outputs)
            f.served_by = SERVED_BY_CLOUD
        else:
            t = time.perf_counter()
            f.outputs = self._compute(
                lambda options: model.run_suffix(k, sent, feeds, run_options=options)
            )
            f.local_s = time.perf_counter() - t
        f.latency_s = time.perf_counter() - started
        f.cpu_s = time.process_time() - cpu_started
        self._emit(f)

    def _compute(self, run: Callable[[Any], Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """Run robot-side model work (`run` gets onnxruntime run options) and wait for it.

        While a hedged frame's reply is still on its way (`_pending`), the work goes to the
        low-priority thread: on a robot short of CPU, receiving that reply then goes first, and
        the learner sees the link, not the robot's later frames. Otherwise it runs here, at the
        loop's own priority (on the testbed's 0.02-core robot, P frames on the low-priority
        thread took a median 0.50 s against 0.40 s here: Zenoh's and the prober's threads
        went first)."""
        pending = self._pending
        if pending is None or pending.call is None or pending.call.settled:
            return dict(run(None))
        assert self._local is not None
        job = self._local.submit(run)
        job.wait()  # as long as the run takes, as if computed in this thread
        if job.error is not None:
            raise job.error
        assert job.outputs is not None
        return job.outputs

    def _position_of(self, decision: Decision) -> int:
        try:
            return self._position[int(decision.action)]
        except (KeyError, ValueError):
            known = ", ".join(str(i) for i in self._position)
            raise UserError(
                f"policy {self.policy.name} chose cut {decision.action!r}; this model has cuts "
                f"{known}"
            ) from None

    def _send(
        self,
        n: int,
        cut: int,
        tensors: dict[str, EncodedTensor],
        epoch: int,
        *,
        background: bool = False,
    ) -> CloudCall:
        request = InferRequest(
            robot=self.robot,
            frame=n,
            model_digest=self.model.digest,
            cut=cut,
            tensors=tensors,
            deadline_s=self.deadline_s,
            sent_at=time.time(),
            epoch=epoch,
        )
        payload = request.to_wire()
        delay = 0.0
        if self._uplink is not None:
            # A frame that cannot get through the emulated uplink before its deadline is not
            # sent: it would only queue ahead of the next frames (the call then times out at the
            # deadline, so the policy still learns what this cut costs).
            delay = self._uplink.delay_for(len(payload))
            if delay < self.deadline_s:
                delay = self._uplink.reserve(len(payload))
            # The encoded size does not depend on the deadline's value (a float is 9 bytes), so
            # re-encoding with the budget left after the emulated uplink keeps the size reserved.
            if 0 < delay < self.deadline_s:
                budget = self.deadline_s - delay
                payload = dataclasses.replace(request, deadline_s=budget).to_wire()
        call = CloudCall(
            self._session,
            self._svc_key,
            payload,
            frame=n,
            budget_s=self.deadline_s,
            delay_s=delay,
            max_reply_bytes=self.config.max_payload_bytes,
        )
        call.start(background=background)
        return call

    def _hedged(self, f: _Frame, k: int, sent: dict[str, np.ndarray]) -> None:
        """Race the cloud against the local suffix and serve whichever result is first.

        The local run is speculative: it starts `decision.hedge_after_s` after the request (the
        policy defers it when the cloud is expected first) and runs on the `LocalRunner`'s
        thread at the lowest CPU priority, so on a robot with a small CPU quota it does not slow
        the offload it hedges (the learner would otherwise see the transfer inflated). A cloud
        reply that comes first serves the frame and cancels the local run (which then reports
        no robot time). A local result that comes first serves the frame; the cloud reply is
        awaited later (`_settle_pending`) to feed the learner. A cloud that fails first (no
        route, busy, an error, the deadline) leaves the local run as the frame's only path: it
        is awaited.
        """
        call = f.call
        assert call is not None and self._local is not None
        wake = threading.Event()
        call.notify(wake)
        cloud_limit = call.deadline_at + FINISH_GRACE_S
        # The policy may defer the local run (`Decision.hedge_after_s`): a reply within that
        # time serves the frame without any local work competing with the offload.
        start_at = min(call.handed_at + f.decision.hedge_after_s, cloud_limit)
        self._wait_until(wake, start_at, lambda: call.settled)
        if call.settled and self._served_by_reply(f):
            return
        model, feeds = self.model, f.feeds
        job = self._local.submit(
            lambda options: model.run_suffix(k, sent, feeds, run_options=options), wake
        )
        self._wait_until(wake, cloud_limit, lambda: job.done or call.settled)
        if not job.done and call.settled and self._served_by_reply(f):
            job.cancel()
            return
        job.wait()  # as long as the run takes, like a fallback computed in this thread
        if job.error is not None:
            raise job.error
        assert job.outputs is not None and job.finished_at is not None
        local_done = job.finished_at
        f.local_s = job.elapsed_s
        if call.settled or time.perf_counter() >= cloud_limit:
            f.result = self._checked(call.result())
            replied_at = f.result.replied_at
            if f.result.reply is not None and replied_at is not None and replied_at <= local_done:
                self._serve_cloud(f, f.result)
            else:
                self._serve_local(f, job.outputs, local_done)
                self._emit(f)
            return
        # The robot's result is first: the frame is served now, its cloud reply comes later.
        self._serve_local(f, job.outputs, local_done)
        self._settle_pending(block=True)  # at most one frame waits for its reply
        self._pending = f

    def _wait_until(self, wake: threading.Event, until: float, done: Callable[[], bool]) -> None:
        """Wait until `done()`, the perf_counter time `until` or a stop; `wake` is set by
        whatever may make `done()` true."""
        while True:  # bounded by `until` (or the stop flag)
            wake.clear()
            left = until - time.perf_counter()
            if done() or left <= 0 or self.should_exit.is_set():
                return
            wake.wait(min(left, STOP_POLL_S))

    def _served_by_reply(self, f: _Frame) -> bool:
        """The cloud call of hedged frame `f` has settled: serve and emit the frame with its
        reply if it brought one (True); else keep the result for later (False)."""
        assert f.call is not None
        f.result = self._checked(f.call.result())
        if f.result.reply is None:
            return False
        self._serve_cloud(f, f.result)
        return True

    @staticmethod
    def _serve_local(f: _Frame, outputs: dict[str, np.ndarray], done_at: float) -> None:
        """Serve hedged frame `f` with the robot's own result, finished at `done_at`."""
        f.outputs, f.latency_s = outputs, done_at - f.started
        f.cpu_s = time.process_time() - f.cpu_started

    def _serve_cloud(self, f: _Frame, result: CallResult) -> None:
        """Serve a hedged frame with its cloud reply (which came first) and emit it."""
        assert result.reply is not None and result.replied_at is not None
        f.outputs = dict(result.reply.outputs)
        f.served_by = SERVED_BY_CLOUD
        f.latency_s = result.replied_at - f.started
        f.cpu_s = time.process_time() - f.cpu_started
        self._emit(f)

    def _settle_pending(self, *, block: bool) -> None:
        f = self._pending
        if f is None or f.call is None:
            return
        call = f.call
        if not block and not call.settled and time.perf_counter() < call.deadline_at:
            return
        finished = call.wait(self.should_exit)
        self._pending = None
        f.result = self._checked(call.result(stopped=not finished))
        self._emit(f)

    def _checked(self, result: CallResult) -> CallResult:
        """A reply whose outputs are not the model's is a decode error (the frame is then
        finished on the robot)."""
        reply = result.reply
        if reply is None:
            return result
        missing = [n for n in self.model.output_names if n not in reply.outputs]
        if missing:
            return dataclasses.replace(
                result,
                reply=None,
                reason=REASON_DECODE_ERROR,
                detail=f"reply from {reply.deployment} lacks output(s) {', '.join(missing)}",
            )
        return result

    # -- after a frame ---------------------------------------------------------------------
    def _emit(self, f: _Frame) -> None:
        """Feed the policy, publish and record the frame."""
        res = f.result
        offloaded = f.decision.action != PURE_ROBOT
        reply = res.reply if res is not None else None
        cloud_s = reply.queue_s + reply.compute_s if reply is not None else 0.0
        if res is None:
            transfer_s = 0.0
        elif reply is not None:
            transfer_s = max(0.0, res.round_trip_s - cloud_s)
        else:
            transfer_s = res.round_trip_s
        fallback = offloaded and reply is None
        reason = res.reason if fallback and res is not None else None
        compute_s = f.prefix_s + (f.local_s or 0.0)
        energy = self._objective.energy_j(f.latency_s, compute_s, transfer_s)
        if offloaded:
            outcome = Outcome(
                prefix_s=f.prefix_s,
                cloud_s=res.round_trip_s if res is not None and reply is not None else None,
                cloud_compute_s=cloud_s if reply is not None else None,
                bytes_up=f.bytes_up,
                local_s=f.local_s,
                latency_s=f.latency_s,
                waited_s=None if reply is not None else self.deadline_s,
            )
        else:
            outcome = Outcome(prefix_s=f.prefix_s, latency_s=f.latency_s)
        self.policy.observe(f.decision, outcome)
        action = None if not offloaded else int(f.decision.action)
        record = TelemetryRecord(
            robot=self.robot,
            frame=f.n,
            action=action_label(action, f.decision.codec),
            bytes_up=f.bytes_up,
            bytes_down=res.bytes_down if res is not None else 0,
            prefix_s=f.prefix_s,
            transfer_s=transfer_s,
            cloud_s=cloud_s,
            suffix_local_s=f.local_s or 0.0,
            latency_s=f.latency_s,
            robot_cpu_s=f.cpu_s,
            energy_j=float(energy),
            deployment=res.deployment if res is not None else None,
            fallback=fallback,
            reason=reason,
            epoch=reply.epoch if reply is not None else f.epoch,
            at=time.time(),
        )
        hedged = f.decision.hedge and offloaded
        self._publish_telemetry(record)
        if self._telemetry is not None:
            detail = res.detail if res is not None and fallback else ""
            self._telemetry.write(
                jsonl_object(
                    record, entropy=f.entropy, hedged=hedged, served_by=f.served_by, detail=detail
                )
            )
        self.summary.add(record, hedged=hedged, served_by=f.served_by)
        self.frames_done += 1
        if reply is not None:
            self._cloud_time.observe(cloud_s)
        if offloaded and res is not None:
            self._track_failures(f.n, res, reply is not None)
        if self._on_result is not None:
            self._on_result(FrameResult(f.n, f.feeds, f.outputs, record, f.served_by, hedged))

    def _publish_telemetry(self, record: TelemetryRecord) -> None:
        try:
            self._tele_pub.put(record.to_wire())
        except zenoh.ZError as exc:
            log.debug("%s: telemetry of frame %d not published: %s", self.robot, record.frame, exc)

    def _publish_probe(self, report: ProbeReport) -> None:
        self._probe_pub.put(report.to_wire())

    def _track_failures(self, n: int, res: CallResult, answered: bool) -> None:
        """Log the start and end of a run of failures (not every frame), and ask for a reroute
        after consecutive timeouts or missing routes."""
        if answered:
            if self._failure_reason is not None:
                log.info(
                    "%s: frame %d answered by %s again after %d frame(s) finished on the robot",
                    self.robot,
                    n,
                    res.deployment,
                    self._failure_streak,
                )
            self._failure_reason, self._failure_streak = None, 0
            return
        reason = res.reason or "unknown"
        if reason != self._failure_reason or self._failure_streak % LOG_FAILURE_EVERY == 0:
            log.warning(
                "%s: frame %d: cloud failed (%s: %s); finished on the robot",
                self.robot,
                n,
                reason,
                res.detail,
            )
        if reason != self._failure_reason:
            self._failure_reason, self._failure_streak = reason, 0
        self._failure_streak += 1
        if reason in FAILOVER_REASONS and self._failure_streak >= REROUTE_AFTER_FAILURES:
            self._request_reroute(reason)

    # -- registry and route ----------------------------------------------------------------
    def _on_route(self, sample: zenoh.Sample) -> None:
        try:
            change = decode(sample.payload.to_bytes(), expect=RouteChange)
        except WireError as exc:
            log.warning("%s: ignoring a bad route message: %s", self.robot, exc)
            return
        self._apply_route(change)

    def _apply_route(self, change: RouteChange) -> None:
        if change.robot != self.robot:
            return
        with self._route_lock:
            if self._route.known and change.epoch < self._route.epoch:
                return  # older than what we hold: epochs only grow
            moved = not self._route.known or change.deployment != self._route.deployment
            self._route = _Route(change.deployment, change.epoch, True)
        if moved:
            log.info(
                "%s: route -> %s (epoch %d, %s)",
                self.robot,
                change.deployment or "local (no deployment)",
                change.epoch,
                change.reason,
            )

    @property
    def route(self) -> tuple[str | None, int]:
        """The deployment the registry last said serves this robot, and its epoch."""
        with self._route_lock:
            return self._route.deployment, self._route.epoch

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._served.set()
        else:
            self._served.clear()

    def _on_registry_token(self, sample: zenoh.Sample) -> None:
        parts = keys.parse_key(str(sample.key_expr))
        if parts is None or parts.id is None:
            return
        with self._members_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._registries.add(parts.id)
            else:
                self._registries.discard(parts.id)
            up = bool(self._registries)
        if up:
            self._registry_down.clear()
            self._registry_up.set()
        else:
            self._registry_up.clear()
            self._registry_down.set()

    def _on_cloud_token(self, sample: zenoh.Sample) -> None:
        parts = keys.parse_key(str(sample.key_expr))
        if parts is None or parts.id is None:
            return
        with self._members_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._clouds.add(parts.id)
            else:
                self._clouds.discard(parts.id)

    def _alive_clouds(self) -> set[str]:
        with self._members_lock:
            return set(self._clouds)

    @property
    def registry_reachable(self) -> bool:
        return self._registry_up.is_set()

    def _watch_registry(self, reported: bool) -> None:
        """Report the registry's reachability (with a growing interval while it is not) and
        register when it appears. `reported`: startup already said it is unreachable. Runs
        until shutdown; every wait is a short slice that checks the stop flag."""
        endpoint = self.config.registry.endpoint
        backoff = REGISTRY_RETRY_INITIAL_S
        if reported:
            self._wait_for(self._registry_up, backoff, self._threads_stop)
            backoff *= 2
        still = " yet" if reported else ""
        while not self._threads_stop.is_set():
            if not self._registry_up.is_set():
                self._report_unreachable(still, backoff)
                self._wait_for(self._registry_up, backoff, self._threads_stop)
                backoff, still = min(backoff * 2, REGISTRY_RETRY_MAX_S), " yet"
                continue
            log.info("%s: registry reachable at %s", self.robot, endpoint)
            backoff, still = REGISTRY_RETRY_INITIAL_S, ""
            self._register()
            self._wait_for(self._registry_down, None, self._threads_stop)
            if self._threads_stop.is_set():
                return
            deployment, epoch = self.route
            log.warning(
                "%s: registry gone; keeping the route to %s (epoch %d), frames go peer to peer; "
                "retrying",
                self.robot,
                deployment or "(none known)",
                epoch,
            )
            # That was the first report: the next one comes after the backoff.
            self._wait_for(self._registry_up, backoff, self._threads_stop)
            backoff, still = backoff * 2, " yet"

    def _report_unreachable(self, still: str, next_s: float) -> None:
        log.warning(
            "%s: registry at %s not reachable%s; frames are finished on the robot unless a "
            "deployment still serves it; retrying (next report in %.0f s)",
            self.robot,
            self.config.registry.endpoint,
            still,
            next_s,
        )

    @staticmethod
    def _wait_for(event: threading.Event, timeout_s: float | None, stop: threading.Event) -> bool:
        """Wait for `event` (at most `timeout_s`, None: no limit) in short slices that give up
        as soon as `stop` is set; True if `event` is set."""
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while not stop.is_set():
            left = WAIT_SLICE_S if end is None else min(WAIT_SLICE_S, end - time.monotonic())
            if left <= 0:
                break
            if event.wait(left):
                return True
        return event.is_set()

    def _register(self) -> None:
        request = RegisterRequest(
            role="robot",
            id=self.robot,
            protocol_version=PROTOCOL_VERSION,
            capabilities=ROBOT_CAPABILITIES,
            service=self.config.service,
            model_digest=self.model.digest,
            software=_software_version(),
        )
        try:
            replies = self._session.get(
                keys.reg_register(self.fleet),
                payload=request.to_wire(),
                timeout=REGISTER_TIMEOUT_S,
            )
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    answer = decode(reply.ok.payload.to_bytes(), expect=RegisterReply)
                except WireError as exc:
                    log.warning("%s: bad registration reply: %s", self.robot, exc)
                    continue
                if not answer.accepted:
                    log.error(
                        "%s: the registry refused this robot: %s; frames are finished on the robot",
                        self.robot,
                        answer.reason,
                    )
                elif answer.route is not None:
                    self._apply_route(answer.route)
                return
        except zenoh.ZError as exc:
            log.debug("%s: registration not sent: %s", self.robot, exc)

    def _request_reroute(self, reason: str) -> None:
        now = time.monotonic()
        if not self._registry_up.is_set() or now - self._last_reroute < REROUTE_MIN_INTERVAL_S:
            return
        self._last_reroute = now
        deployment, epoch = self.route
        request = RerouteRequest(
            robot=self.robot,
            deployment=deployment,
            epoch=epoch,
            reason=reason,
            consecutive_timeouts=self._failure_streak,
        )

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                change = decode(reply.ok.payload.to_bytes(), expect=RouteChange)
            except WireError:
                return  # an ErrorReply: the registry could not move us; telemetry tells it more
            self._apply_route(change)

        try:
            self._session.get(
                keys.reg_reroute(self.fleet),
                on_reply,
                payload=request.to_wire(),
                timeout=REROUTE_TIMEOUT_S,
            )
            log.info(
                "%s: asked the registry for a new route after %d frame(s) of %s",
                self.robot,
                self._failure_streak,
                reason,
            )
        except zenoh.ZError as exc:
            log.debug("%s: reroute request not sent: %s", self.robot, exc)


def _software_version() -> str:
    try:
        return metadata.version("elasticfog")
    except metadata.PackageNotFoundError:
        return ""
