"""The robot daemon (`elasticfog robot`): the per-frame split loop, over Zenoh.

Lifecycle (`common.daemon.Daemon`: startup -> main loop -> shutdown, in reverse order):

1. Load the split model (one set of shared-weight onnxruntime sessions, every cut warmed up),
   start the low-priority local-run thread, build the policy from a robot-side profile, open the
   frame source and the `--telemetry` file.
2. Open a Zenoh *peer* session connected to the registry endpoint only (the robot's config names
   no cloud host: it finds deployments through the registry's router and queries its anycast
   service key). Declare the telemetry and probe publishers, the route subscriber (handled by
   the registry link), one membership view of the registry and the clouds (`common.membership`),
   and a querier on the service key whose matching listener says when a deployment serves it.
3. Start the prober, then announce the liveliness token `alive/robot/<id>`.
4. Wait (bounded, cut short by a signal) for the registry, start the registry link's watcher
   (`robotd.registry_link`), then wait for a deployment serving the robot.

Each step hands what it made to the lifecycle (`Daemon.hold`, `on_release`, `announce`), which
releases it all at shutdown in reverse order, the token first, also after a failed startup; the
session is closed explicitly (a session still holding callbacks at exit hangs the process).
Every Zenoh callback is `guarded`: bad input is one throttled line, never a traceback into Zenoh.
`main_loop` runs frames until `--frames`, the source's end or a signal.

A frame (DESIGN.md, "A frame's life"): grab → entropy → `policy.decide` → prefix (or the whole
model for P) → encoded `InferRequest` → (emulated uplink) → `get` on the service key with the
deadline → reply, or the robot runs the suffix itself with the reason (`robotd.offload`) →
`policy.observe` → telemetry (`robotd.telemetry_sink`: `tele/<robot>`, JSONL file, run summary). No
frame is ever lost. With `max_in_flight` N > 1 an offloaded frame is not awaited: up to N are in
flight at once (`robotd.pipeline`: the loop sends frame k while k-1... are computed), each with
its own deadline and local finish, and results are applied in frame order (an older one is stale:
dropped and counted). A hedged decision also runs the local suffix speculatively (at once, or
deferred by the policy while the reply is expected first) on a thread of the lowest CPU priority
(`robotd.offload.LocalRunner`), so that on a robot short of CPU it does not slow the offload it
hedges, and serves whichever result is ready first. A cloud reply first cancels the local run;
when the robot's result wins, the frame is served and the loop moves on while the cloud's reply
(at most one such frame in flight) is awaited up to its deadline, to feed the learner; meanwhile
the next frames' model runs go to the low-priority thread too (`robotd.model_runs`).

Beside the daemon: `robotd.registry_link.RegistryLink` (registration, the route and its epoch,
reroute requests, the "registry unreachable" reports), `robotd.robot_model` (the split model
loaded at startup, its camera input, cut positions, replies checked against its outputs),
`robotd.service_match` (whether a deployment serves the service key), `robotd.request_sender`
(the request on the service key, through the emulated uplink), `robotd.frame` (a frame's
accounting), `robotd.telemetry_sink` (where each frame's record and each probe report go),
`robotd.failure_runs` (runs of cloud failures, and when they call for a reroute),
`robotd.robot_profile` (the startup profile and policy) and `robotd.emulation` (on one host: a
robot `--robot-slowdown` times slower than the host, every robot-side model run stretched by a
wait, and `--phases` that change it and the emulated uplink at frame boundaries; the telemetry
file records each frame's phase).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common import keys
from common.config import FleetConfig
from common.daemon import Daemon
from common.errors import UserError
from common.keys import Role
from common.membership import MemberChange, MembershipView
from common.partition.runtime import SplitModel
from common.session import open_session
from common.wire.tensor_codecs import encode_tensor_as
from robotd.emulation import (
    Emulation,
    Phase,
    Slowdown,
    check_slowdown,
    emulation_note,
    scaled_profile,
)
from robotd.entropy import frame_entropy
from robotd.failure_runs import FailureRuns
from robotd.frame import Frame, FrameResult
from robotd.model_runs import ModelRuns
from robotd.offload import FINISH_GRACE_S, STOP_POLL_S, LocalRunner
from robotd.pacing import FramePacer, TokenBucket
from robotd.pipeline import FramePipeline, InFlight, ResultOrder
from robotd.policies import PURE_ROBOT, FrameContext, Objective, Policy
from robotd.pool_turns import PoolTurns
from robotd.probes import PROBE_INTERVAL_S, CloudTime, Prober, probe_padding_bytes
from robotd.registry_link import REGISTRY_RETRY_INITIAL_S, RegistryLink
from robotd.request_sender import RequestSender
from robotd.robot_model import RobotModel, open_split_model
from robotd.robot_profile import build_policy, robot_profile, warm_up
from robotd.service_match import ServiceMatch
from robotd.source_names import SourceSpec, parse_source
from robotd.sources import EndOfStream, FrameSource
from robotd.stereo_frame import CameraFrame, first_view
from robotd.telemetry import SERVED_BY_CLOUD, RemoteTimes, RunSummary, TelemetryFile
from robotd.telemetry_sink import TelemetrySink

# `robot_profile` is imported from here by the benchmarks (it lived in this module).
__all__ = ["FrameResult", "RobotDaemon", "RobotOptions", "robot_profile"]

log = logging.getLogger("robotd")

# How long startup waits for the registry's token, then for a deployment serving the robot, so
# the first frames are not finished locally only because the session was still meeting peers.
REGISTRY_WAIT_S = 2.0
ROUTE_WAIT_S = 3.0

# What finishing an offloaded frame in flight needs: the frame, its cut position, the tensors sent.
Offload = tuple[Frame, int, dict[str, np.ndarray]]


@dataclass
class RobotOptions:
    """Run options of the robot daemon; None takes the machine's value from fleet.yaml."""

    source: str | SourceSpec | None = None
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
    robot_slowdown: float = 1.0
    phases: tuple[Phase, ...] = ()
    max_in_flight: int | None = None

    @property
    def initial_slowdown(self) -> float:
        """The emulated slowdown of the first frames (the first phase's, if any)."""
        return self.phases[0].slowdown if self.phases else self.robot_slowdown

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
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise UserError(f"--max-in-flight must be at least 1, got {self.max_in_flight}")
        check_slowdown(self.robot_slowdown)


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
        self.machine = config.machine(robot_id, role=Role.ROBOT)
        self.robot = robot_id
        self.options = options or RobotOptions()
        self.options.check()
        self.fleet = config.fleet
        self.deadline_s = config.deadline_s
        self.source_spec = parse_source(self.options.source or self.machine.source)
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
        self._served = ServiceMatch()
        self._cloud_time = CloudTime()
        self._pending: Frame | None = None
        self._failures = FailureRuns(robot_id)
        self._turns = PoolTurns()  # round robin: the pool member of the next offloaded frame
        # Offloaded frames in flight (`robotd.pipeline`); results applied in frame order.
        self.max_in_flight = self.options.max_in_flight or self.machine.max_in_flight
        self._order = ResultOrder()
        self._pipeline = FramePipeline[Offload](
            self.max_in_flight, self._finish_offload, self.should_exit
        )
        # Publications, file and summary of the frames; what they go to is made in startup.
        self._sink = TelemetrySink(robot_id, self.summary)
        # Made in startup, released by the lifecycle.
        self.model: SplitModel
        self._robot_model: RobotModel
        self.policy: Policy
        self._link: RegistryLink | None = None
        self._source: FrameSource
        self._requests: RequestSender
        self._local: LocalRunner | None = None
        self._runs: ModelRuns
        # Emulation (`robotd.emulation`): every robot-side model run goes through the slowdown;
        # phases switch it and the uplink at frame boundaries.
        self._slowdown = Slowdown(self.options.initial_slowdown, stop=self.should_exit)
        self._emulation: Emulation

    # -- public ----------------------------------------------------------------------------
    @property
    def link(self) -> RegistryLink:
        """The link to the registry (made in startup, once the session is open)."""
        if self._link is None:
            raise RuntimeError("the registry link is made in startup()")
        return self._link

    @property
    def route(self) -> tuple[str | None, int]:
        """The deployment the registry last said serves this robot, and its epoch."""
        return self._link.route if self._link is not None else (None, 0)

    @property
    def registry_reachable(self) -> bool:
        return self._link is not None and self._link.reachable

    # -- lifecycle -------------------------------------------------------------------------
    def startup(self) -> None:
        cfg = self.config
        self.model = self.hold(open_split_model(cfg, self.machine), "model sessions")
        self._robot_model = robot_model = RobotModel(self.model, cfg.model)
        warm_up(self.model, robot_model.sample_feeds)
        self._local = local = LocalRunner(f"local-run-{self.robot}")
        local.start()
        self.on_release(local.stop, what="local-run thread")
        self._runs = ModelRuns(self._slowdown, local)
        self.policy = self._policy_override or build_policy(
            self.policy_spec,
            cfg,
            scaled_profile(
                robot_model.profile(
                    cfg,
                    source_spec=self.source_spec,
                    seed=self.options.seed,
                    threads=self.machine.threads,
                    policy_spec=self.policy_spec,
                ),
                self._slowdown.factor,
            ),
            self._objective,
        )
        self._source = self.hold(
            robot_model.open_source(self.source_spec, seed=self.options.seed),
            "frame source",
        )
        if self.options.telemetry is not None:
            self._sink.file = self.hold(TelemetryFile(self.options.telemetry), "telemetry file")
        self._open_zenoh()
        log.info(
            "%s: model %s (%d cuts, digest %s), policy %s, source %s, deadline %.3f s, "
            "registry %s%s%s",
            self.robot,
            cfg.model,
            self.model.num_cuts,
            self.model.digest[:12],
            self.policy.name,
            self._source.description,
            self.deadline_s,
            cfg.registry.endpoint,
            f", {self.max_in_flight} frames in flight" if self.max_in_flight > 1 else "",
            # Phases describe themselves as they start.
            "" if self.options.phases else emulation_note(self.uplink_mbit, self._slowdown.factor),
        )
        self._warn_if_refused_past_limit()
        self._wait_for_fleet()

    def _warn_if_refused_past_limit(self) -> None:
        """A robot with more frames in flight than a deployment admits per robot gets `busy`
        there for the rest (finished on the robot: nothing is lost, but the overlap is not)."""
        short = self.config.short_of_in_flight(self.max_in_flight)
        if short:
            log.warning(
                "%s: %d frames in flight, but %s admit(s) fewer of one robot's requests at once "
                "(batching.max_in_flight_per_robot): frames past that are answered busy there "
                "and finished here",
                self.robot,
                self.max_in_flight,
                ", ".join(f"{c} ({limit})" for c, limit in short.items()),
            )

    def _open_zenoh(self) -> None:
        cfg = self.config
        session = self.hold(open_session(cfg, machine=self.robot), "zenoh session")
        self._requests = RequestSender(
            session,
            self._svc_key,
            robot=self.robot,
            model_digest=self.model.digest,
            deadline_s=self.deadline_s,
            max_reply_bytes=cfg.max_payload_bytes,
            uplink=None if self.uplink_mbit is None else TokenBucket.from_mbit(self.uplink_mbit),
            member_key=functools.partial(keys.svc_infer_at, self.fleet, cfg.service, self.robot),
        )
        self._emulation = Emulation(
            self.options.phases, self._slowdown, self._set_uplink, robot=self.robot
        )
        self._link = link = RegistryLink(
            session,
            cfg,
            self.robot,
            model_digest=self.model.digest,
            throttled=self.throttled,
            guard=self.guarded,
            max_in_flight=self.max_in_flight,
        )
        self._sink.declare(self, session, self.fleet)
        route_key = keys.route(self.fleet, self.robot)
        self.hold(
            session.declare_subscriber(
                route_key, self.guarded(link.on_route, what=f"a message on {route_key}")
            ),
            "route subscriber",
        )
        members = self.hold(
            MembershipView(
                session,
                self.fleet,
                roles=("registry", "cloud"),
                on_change=self.guarded(self._on_member, what="a membership change"),
            ),
            "membership view",
        )
        # A querier on the service key only to be told when a deployment serves it (frames use
        # session.get: each has its own timeout).
        self._served.declare(self, session, self._svc_key)
        padding = self.options.probe_padding_bytes
        if padding is None:
            padding = probe_padding_bytes([c.bytes for c in self.model.partition.cuts])
        prober = Prober(
            session,
            self.fleet,
            self.robot,
            max_padding_bytes=padding,
            publish=self._sink.probe,
            alive_clouds=lambda: set(members.ids("cloud")),
            cloud_time=self._cloud_time,
            interval_s=self.options.probe_interval_s,
            max_reply_bytes=cfg.max_payload_bytes,
        )
        prober.start()
        self.on_release(prober.stop, what="prober")
        # Ready: announce the robot last; the lifecycle takes the token down first at shutdown.
        self.announce(session.liveliness().declare_token(keys.alive_robot(self.fleet, self.robot)))

    def _wait_for_fleet(self) -> None:
        """Give the session a moment to meet the registry and the deployment serving this robot
        (bounded, and cut short by a signal; frames are finished locally meanwhile anyway), then
        leave the registry to the link's watcher thread."""
        link = self.link
        reachable = link.wait_reachable(self.options.registry_wait_s, self.should_exit)
        if not reachable:
            link.report_unreachable("", REGISTRY_RETRY_INITIAL_S)
        link.start(reported=not reachable)
        self.on_release(link.stop, what="registry watcher")
        if reachable and not self._served.wait(self.options.route_wait_s, self.should_exit):
            log.info(
                "%s: no deployment serves %s yet; frames are finished on the robot until one does",
                self.robot,
                self._svc_key,
            )

    def shutdown(self) -> None:
        """Let go of a hedged frame's reply still awaited (it may be waiting for the emulated
        uplink), then release everything startup made: the token first, then in reverse."""
        pending = self._pending
        if pending is not None and pending.call is not None:
            pending.call.cancel()
        self._pipeline.cancel()  # frames in flight after a loop that failed
        super().shutdown()

    # -- callbacks -------------------------------------------------------------------------
    def _on_member(self, change: MemberChange) -> None:
        if change.role == "registry":
            self.link.registry_changed(bool(change.alive_ids))

    def _set_uplink(self, bucket: TokenBucket | None) -> None:
        """A phase's emulated uplink (None: requests are not paced)."""
        self._requests.uplink = bucket

    # -- the frame loop --------------------------------------------------------------------
    def main_loop(self) -> None:
        pacer = FramePacer(self.fps)
        limit = self.options.frames
        self.summary.started_at = time.perf_counter()
        n = 0
        # Bounded by --frames, or by the stop flag (signals) otherwise.
        while limit is None or n < limit:
            # The wait for the next frame's start also finishes frames in flight that settle.
            if not self._pipeline.idle(pacer.delay()):
                break
            self._settle_pending(block=False)
            self._emulation.enter(n)
            try:
                frame = self._source.read()
            except EndOfStream:
                log.info("%s: %s ended after %d frames", self.robot, self._source.description, n)
                break
            stamp_ns = self._source.last_stamp_ns
            self.run_frame(n, frame, stamp_ns=stamp_ns if stamp_ns is not None else time.time_ns())
            n += 1
        self._pipeline.drain()
        self._settle_pending(block=True)
        self.summary.ended_at = time.perf_counter()
        if self.should_exit.is_set() and limit is not None and n < limit:
            log.info("%s: stopped after %d of %d frames", self.robot, n, limit)

    def run_frame(self, n: int, frame: CameraFrame, *, stamp_ns: int = 0) -> None:
        """Run one frame to completion, or hand it to the pipeline (`robotd.pipeline`), or (hedged,
        the robot's result first) to where it is served; its cloud reply is settled later."""
        started = time.perf_counter()
        cpu_started = time.process_time()
        feeds = self._robot_model.feeds(frame)
        entropy = frame_entropy(first_view(frame))
        decision = self.policy.decide(FrameContext(index=n, entropy=entropy))
        held = self.link.held
        epoch = held.epoch
        f = Frame(n, decision, entropy, feeds, started, cpu_started, epoch, stamp_ns)
        model = self.model
        if decision.action == PURE_ROBOT:
            f.outputs = self._compute(lambda options: model.run_full(feeds, run_options=options))
            f.prefix_s = f.latency_s = time.perf_counter() - started
            f.cpu_s = time.process_time() - cpu_started
            self._emit(f)
            return
        k = self._robot_model.position_of(decision, self.policy.name)
        cut = self.model.partition.cuts[k]
        t = time.perf_counter()
        sent = self._compute(lambda options: model.run_prefix(k, feeds, run_options=options))
        # Encoding is the robot's part of the action: it counts in its prefix time.
        encoded = {name: encode_tensor_as(a, decision.codec) for name, a in sent.items()}
        f.prefix_s = time.perf_counter() - t
        # In flight beside other frames, the request is handed to Zenoh from a thread of its own.
        background = decision.hedge or self.max_in_flight > 1
        f.call = call = self._requests.send(
            n,
            cut.index,
            encoded,
            epoch,
            background=background,
            end=decision.end,
            member=self._turns.next(held.pool),
        )
        f.bytes_up = call.bytes_up
        if decision.hedge:
            self._hedged(f, k, sent)
            return
        self._pipeline.submit(InFlight(n, call, (f, k, sent)))

    def _finish_offload(self, item: InFlight[Offload]) -> None:
        """Finish an offloaded frame at its reply, or on the robot (a failure, the deadline)."""
        f, k, sent = item.work
        call, feeds, model = f.call, f.feeds, self.model
        assert call is not None
        finished = call.wait(self.should_exit)
        end = f.decision.end
        f.result = self._robot_model.checked(call.result(stopped=not finished), end)
        if f.result.reply is not None:
            f.outputs = dict(f.result.reply.outputs)
            f.served_by = SERVED_BY_CLOUD
            if end is not None:  # a segment: the robot runs the tail from the reply's tensors
                t, reply = time.perf_counter(), f.outputs
                f.outputs = self._compute(
                    lambda options: model.run_suffix(end, reply, run_options=options)
                )
                f.prefix_s += time.perf_counter() - t  # the robot's own part of the action
        else:
            t = time.perf_counter()
            f.outputs = self._compute(
                lambda options: model.run_suffix(k, sent, feeds, run_options=options)
            )
            f.local_s = time.perf_counter() - t
        f.latency_s = time.perf_counter() - f.started
        f.cpu_s = time.process_time() - f.cpu_started
        self._emit(f)

    def _compute(self, run: Callable[[Any], Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """Run robot-side model work and wait for it (where it runs: `robotd.model_runs`)."""
        return self._runs.run(run, self._pending)

    def _hedged(self, f: Frame, k: int, sent: dict[str, np.ndarray]) -> None:
        """Race the cloud against the local suffix and serve whichever result is first.

        The local run is speculative: it starts `decision.hedge_after_s` after the request (the
        policy defers it when the cloud is expected first) and runs on the `LocalRunner`'s
        thread at the lowest CPU priority, so on a robot with a small CPU quota it does not slow
        the offload it hedges (the learner would otherwise see the transfer inflated). A cloud
        reply that comes first serves the frame and cancels the local run (which then reports
        no robot time). A local result that comes first serves the frame; the cloud reply is
        awaited later (`_settle_pending`) to feed the learner. A cloud that fails first (no
        route, busy, an error, the deadline) leaves the local run as the frame's only path: it
        is awaited. When the policy expects the local run to serve the frame, it is not
        speculative and runs at once in this thread (`_local_first`).
        """
        if f.decision.local_expected:
            self._local_first(f, k, sent)
            return
        call = f.call
        assert call is not None and self._local is not None
        wake = threading.Event()
        call.notify(wake)
        cloud_limit = call.deadline_at + FINISH_GRACE_S
        # The policy may defer the local run (`Decision.hedge_after_s`): a reply within that
        # time serves the frame without any local work competing with the offload.
        start_at = min(call.handed_at + f.decision.hedge_after_s, cloud_limit)
        _wait_until(self.should_exit, wake, start_at, lambda: call.settled)
        if call.settled and self._served_by_reply(f):
            return
        model, feeds = self.model, f.feeds
        job = self._local.submit(
            self._slowdown.stretched(
                lambda options: model.run_suffix(k, sent, feeds, run_options=options)
            ),
            wake,
        )
        _wait_until(self.should_exit, wake, cloud_limit, lambda: job.done or call.settled)
        if not job.done and call.settled and self._served_by_reply(f):
            job.cancel()
            return
        job.wait()  # as long as the run takes, like a fallback computed in this thread
        if job.error is not None:
            raise job.error
        assert job.outputs is not None and job.finished_at is not None
        f.local_s = job.elapsed_s
        self._serve_first(f, job.outputs, job.finished_at, cloud_limit)

    def _local_first(self, f: Frame, k: int, sent: dict[str, np.ndarray]) -> None:
        """A hedged frame whose local run is its expected path (`Decision.local_expected`: the
        estimates favour P, the request is exploration). The local suffix runs here at once, at
        the loop's priority: on the speculative low-priority thread, a 0.5-core robot's forced
        samples took 0.12-0.17 s for a 65 ms model (the offload's threads went first), which
        made every forced sample cost latency. A reply that came first still serves the frame."""
        call = f.call
        assert call is not None
        started = time.perf_counter()
        model, feeds = self.model, f.feeds
        outputs = dict(
            self._slowdown.run(
                lambda options: model.run_suffix(k, sent, feeds, run_options=options), None
            )
        )
        local_done = time.perf_counter()
        f.local_s = local_done - started
        self._serve_first(f, outputs, local_done, call.deadline_at + FINISH_GRACE_S)

    def _serve_first(
        self, f: Frame, outputs: dict[str, np.ndarray], local_done: float, cloud_limit: float
    ) -> None:
        """Hedged frame `f` has its local result (finished at `local_done`): serve it with
        whichever of that and the cloud reply came first; a reply still on its way is settled
        later (`_settle_pending`) to feed the learner."""
        call = f.call
        assert call is not None
        if call.settled or time.perf_counter() >= cloud_limit:
            f.result = self._robot_model.checked(call.result())
            replied_at = f.result.replied_at
            if f.result.reply is not None and replied_at is not None and replied_at <= local_done:
                self._serve_cloud(f)
            else:
                f.serve_local(outputs, local_done)
                self._emit(f)
            return
        # The robot's result is first: the frame is served (applied) now, its reply comes later.
        f.serve_local(outputs, local_done)
        f.stale = not self._order.admit(f.n)
        self._settle_pending(block=True)  # at most one frame waits for its reply
        self._pending = f

    def _served_by_reply(self, f: Frame) -> bool:
        """The cloud call of hedged frame `f` has settled: serve and emit the frame with its
        reply if it brought one (True); else keep the result for later (False)."""
        assert f.call is not None
        f.result = self._robot_model.checked(f.call.result())
        if f.result.reply is None:
            return False
        self._serve_cloud(f)
        return True

    def _serve_cloud(self, f: Frame) -> None:
        """Serve a hedged frame with its cloud reply (which came first) and emit it."""
        assert f.result is not None
        f.serve_cloud(f.result)
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
        f.result = self._robot_model.checked(call.result(stopped=not finished))
        self._emit(f)

    # -- after a frame ---------------------------------------------------------------------
    def _emit(self, f: Frame) -> None:
        """Feed the policy, publish and record the frame, act on a run of cloud failures, and
        hand an applied frame's result to `on_result`, then to the source."""
        res = f.result
        remote = RemoteTimes.of(res)
        compute_s = f.prefix_s + (f.local_s or 0.0)
        energy = self._objective.energy_j(f.latency_s, compute_s, remote.transfer_s)
        self.policy.observe(f.decision, f.outcome(self.deadline_s))
        if f.stale is None:  # applied now, unless a newer frame's result was
            f.stale = not self._order.admit(f.n)
        record = f.record(self.robot, energy)
        self._sink.frame(f, record, phase=self._emulation.phase_name(f.n))
        self.frames_done += 1
        if res is not None and res.reply is not None:
            self._cloud_time.observe(remote.cloud_s)
        if f.offloaded and res is not None:
            reroute = self._failures.note(f.n, res)
            if reroute is not None:
                self.link.request_reroute(reroute, self._failures.streak)
        if not f.stale:
            result = FrameResult(f.n, f.feeds, f.outputs, record, f.served_by, f.hedged, f.stamp_ns)
            if self._on_result is not None:
                self._on_result(result)
            self._source.on_result(result)


def _wait_until(
    stop: threading.Event, wake: threading.Event, until: float, done: Callable[[], bool]
) -> None:
    """Wait until `done()`, the perf_counter time `until` or `stop`; `wake` is set by whatever
    may make `done()` true."""
    while True:  # bounded by `until` (or the stop flag)
        wake.clear()
        left = until - time.perf_counter()
        if done() or left <= 0 or stop.is_set():
            return
        wake.wait(min(left, STOP_POLL_S))
