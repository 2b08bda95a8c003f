"""The robot's frame and hedging loop: each frame from the source to its applied result.

A frame (DESIGN.md, "A frame's life"): grab → entropy → `policy.decide` → prefix (or the whole
model for P) → encoded `InferRequest` → (emulated uplink) → `get` on the service key with the
deadline → reply, or the robot runs the suffix itself with the reason (`robotd.frame_path.offload`)
→
`policy.observe` → telemetry (`robotd.telemetry_sink`: `tele/<robot>`, JSONL file, run summary). No
frame is ever lost. With `max_in_flight` N > 1 an offloaded frame is not awaited: up to N are in
flight at once (`robotd.frame_path.pipeline`: the loop sends frame k while k-1... are computed),
each with its own deadline and local finish, and results are applied in frame order (an older one is
stale: dropped and counted). A hedged decision also runs the local suffix speculatively (at once, or
deferred by the policy while the reply is expected first) on a thread of the lowest CPU priority
(`robotd.frame_path.local_runs.LocalRunner`), so that on a robot short of CPU it does not slow the
offload it hedges, and serves whichever result is ready first. A cloud reply first cancels the local
run; when the robot's result wins, the frame is served and the loop moves on while the cloud's reply
(at most one such frame in flight) is awaited up to its deadline, to feed the learner; meanwhile
the next frames' model runs go to the low-priority thread too (`robotd.frame_path.model_runs`).

`FrameLoop` takes what the robot daemon made at startup (the split model, the policy, the
source, the request sender, the registry link, the sinks) and opens nothing itself: the daemon
(`robotd.daemon`) keeps startup, resources and shutdown, and calls `run`. A robot whose source
had no frame at start (`zenoh`, `ros2:`) starts on raw actions and has a `refinement`
(`robotd.robot_profile.FirstFramesRefinement`): once its first frames are served, the frames in
flight are finished (each decision observed by the policy that made it), the codecs are measured
on those frames, and the policy built on them takes over. This happens once, on this thread,
between two frames; frames that arrive meanwhile wait as any frame does (the newest is kept).

A video action (`h264`, cut 0) codes the frame in the stream of the deployment it goes to
(`robotd.frame_path.video_streams.VideoEncoders`): the policy is told before deciding whether
that frame would be a keyframe (`FrameContext.keyframe`), a frame served without a video frame
breaks the streams (the next is a keyframe), one whose request was refused, lost or timed out
marks its stream unseen, and a frame the deployment could not decode is resent as a keyframe
within its deadline (`robotd.frame_path.offload.CloudCall`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from common.partition.runtime import SplitModel
from common.throttled_log import ThrottledLog
from common.wire.robot_to_cloud import VideoStream
from common.wire.telemetry import TelemetryRecord
from common.wire.tensor_codecs import EncodedTensor, encode_tensor_as, is_video
from robotd.emulation import Emulation, Slowdown
from robotd.frame_path.entropy import frame_entropy
from robotd.frame_path.failure_runs import FailureRuns
from robotd.frame_path.frame import Frame, FrameResult
from robotd.frame_path.local_runs import LocalRunner
from robotd.frame_path.model_runs import ModelRuns
from robotd.frame_path.offload import FINISH_GRACE_S, STOP_POLL_S
from robotd.frame_path.pacing import FramePacer, TimelinePacer
from robotd.frame_path.pipeline import FramePipeline, InFlight, ResultOrder
from robotd.frame_path.pool_turns import PoolTurns
from robotd.frame_path.probes import CloudTime
from robotd.frame_path.registry_link import RegistryLink
from robotd.frame_path.request_sender import RequestSender
from robotd.frame_path.video_streams import VideoEncoders
from robotd.policies import PURE_ROBOT, FrameContext, Objective, Policy
from robotd.results.sinks import ResultSink
from robotd.robot_model import RobotModel
from robotd.robot_profile import FirstFramesRefinement
from robotd.sources.frame_sources import EndOfStream, FrameSource
from robotd.sources.stereo_frame import CameraFrame, first_view
from robotd.telemetry import SERVED_BY_CLOUD, RemoteTimes, RunSummary
from robotd.telemetry_sink import TelemetrySink

log = logging.getLogger("robotd")

# While a source waits for its sender, frames in flight are looked at this often.
FRAME_POLL_S = 0.005

# What finishing an offloaded frame in flight needs: the frame, its cut position, the tensors sent.
Offload = tuple[Frame, int, dict[str, np.ndarray]]


@dataclass
class FrameLoop:
    """The frame loop of one robot over the parts its daemon made (see the module docstring).
    Only the daemon's main thread calls it; `cancel` (shutdown) lets go of what is in flight."""

    robot: str
    model: SplitModel
    robot_model: RobotModel
    policy: Policy
    objective: Objective
    deadline_s: float
    source: FrameSource
    requests: RequestSender
    link: RegistryLink
    runs: ModelRuns
    local: LocalRunner
    slowdown: Slowdown
    emulation: Emulation
    sink: TelemetrySink
    summary: RunSummary
    cloud_time: CloudTime
    stop: threading.Event
    throttled: ThrottledLog
    max_in_flight: int = 1
    result_sinks: list[ResultSink] = field(default_factory=list)
    """Where each applied frame's result goes (the daemon's list: sinks added later count)."""
    on_result: Callable[[FrameResult], None] | None = None
    refinement: FirstFramesRefinement | None = None
    """The policy measured on the first frames served, when the source had none at start."""
    video: VideoEncoders = field(default_factory=VideoEncoders)
    """The video streams of `h264` actions, one per deployment sent to."""
    frames_done: int = 0

    def __post_init__(self) -> None:
        self._failures = FailureRuns(self.robot)
        self._turns = PoolTurns()  # round robin: the pool member of the next offloaded frame
        self._order = ResultOrder()
        self._pipeline = FramePipeline[Offload](self.max_in_flight, self._finish_offload, self.stop)
        self._pending: Frame | None = None

    def cancel(self) -> None:
        """Let go of a hedged frame's reply still awaited (it may be waiting for the emulated
        uplink) and of the frames in flight (after a loop that failed)."""
        pending = self._pending
        if pending is not None and pending.call is not None:
            pending.call.cancel()
        self._pipeline.cancel()

    def run(
        self,
        *,
        frames: int | None,
        fps: float | None,
        pacer: FramePacer | TimelinePacer | None = None,
    ) -> None:
        """Frames until `frames` (None: no limit), the source's end or the stop flag, paced by
        `pacer` (a recording's timeline), else at `fps` (None: as fast as frames complete); then
        the frames in flight are finished."""
        pacer = pacer if pacer is not None else FramePacer(fps)
        limit = frames
        self.summary.started_at = time.perf_counter()
        n = dropped_seen = 0
        # Bounded by --frames, or by the stop flag (signals) otherwise.
        while limit is None or n < limit:
            # The wait for the next frame's start also finishes frames in flight that settle.
            if not self._pipeline.idle(pacer.delay()) or not self._await_frame():
                break
            self._settle_pending(block=False)
            self.emulation.enter(n)
            try:
                frame = self.source.read()
            except EndOfStream:
                log.info("%s: %s ended after %d frames", self.robot, self.source.description, n)
                break
            stamp_ns = self.source.last_stamp_ns
            # Frames the source dropped unread since the last read (a newer one had arrived).
            total_dropped = self.source.dropped_stale
            dropped, dropped_seen = total_dropped - dropped_seen, total_dropped
            self.run_frame(
                n,
                frame,
                stamp_ns=stamp_ns if stamp_ns is not None else time.time_ns(),
                dropped_stale=dropped,
            )
            n += 1
            refinement = self.refinement
            if refinement is not None and refinement.offer(self.robot_model.feeds(frame)):
                self._refine(refinement)
        self._pipeline.drain()
        self._settle_pending(block=True)
        self.summary.ended_at = time.perf_counter()
        self.summary.dropped_stale = self.source.dropped_stale
        self.summary.rejected_frames = self.source.rejected_frames()
        if self.stop.is_set() and limit is not None and n < limit:
            log.info("%s: stopped after %d of %d frames", self.robot, n, limit)

    def _refine(self, refinement: FirstFramesRefinement) -> None:
        """Hand the frames to the policy measured on the first frames served, once: the frames
        in flight are finished first, so the policy that decided each frame observes it."""
        self.refinement = None
        self._pipeline.drain()
        self._settle_pending(block=True)
        policy = refinement.refined(self.stop)
        if policy is not None:
            self.policy = policy

    def _await_frame(self) -> bool:
        """Until the source has a frame to read (one fed by others waits for its sender),
        finishing the frames in flight that settle meanwhile, so their results are not held
        back by a quiet sender; False when the robot is stopping."""
        while not self.source.wait_ready(FRAME_POLL_S):  # bounded by the stop flag
            if not self._pipeline.idle(0.0):
                return False
            self._settle_pending(block=False)
        return True

    def run_frame(
        self, n: int, frame: CameraFrame, *, stamp_ns: int = 0, dropped_stale: int = 0
    ) -> None:
        """Run one frame to completion, or hand it to the pipeline (`robotd.frame_path.pipeline`),
        or (hedged, the robot's result first) to where it is served; its cloud reply is settled
        later."""
        started = time.perf_counter()
        cpu_started = time.process_time()
        feeds = self.robot_model.feeds(frame)
        entropy = frame_entropy(first_view(frame))
        held = self.link.held
        epoch = held.epoch
        keyframe = self.video.keyframe_due(self._turns.peek(held.pool) or held.deployment, epoch)
        context = FrameContext(index=n, entropy=entropy, keyframe=keyframe)
        decision = self.policy.decide(context)
        video = decision.action != PURE_ROBOT and is_video(decision.codec)
        if not video:
            self.video.skipped()  # the camera's sequence is broken: the next video is a key
        f = Frame(n, decision, entropy, feeds, started, cpu_started, epoch, stamp_ns)
        f.dropped_stale = dropped_stale
        model = self.model
        if decision.action == PURE_ROBOT:
            f.outputs = self._compute(lambda options: model.run_full(feeds, run_options=options))
            f.prefix_s = f.latency_s = time.perf_counter() - started
            f.cpu_s = time.process_time() - cpu_started
            self._emit(f)
            return
        k = self.robot_model.position_of(decision, self.policy.name)
        cut = self.model.partition.cuts[k]
        t = time.perf_counter()
        sent = self._compute(lambda options: model.run_prefix(k, feeds, run_options=options))
        member = self._turns.next(held.pool)
        streamed: dict[str, Any] = {}  # a video frame's stream position and keyframe resend
        # Encoding is the robot's part of the action: it counts in its prefix time.
        if video:
            f.video_at = where = member or held.deployment or ""
            encoded, stream = self.video.encode(n, where, epoch, sent)

            def rekey() -> tuple[dict[str, EncodedTensor], VideoStream]:
                return self.video.encode(n, where, epoch, sent, keyframe=True)

            streamed = {"video": stream, "keyframe": rekey}
        else:
            encoded = {name: encode_tensor_as(a, decision.codec) for name, a in sent.items()}
        f.prefix_s = time.perf_counter() - t
        # In flight beside other frames, the request is handed to Zenoh from a thread of its own.
        background = decision.hedge or self.max_in_flight > 1
        f.call = call = self.requests.send(
            n,
            cut.index,
            encoded,
            epoch,
            background=background,
            end=decision.end,
            member=member,
            **streamed,
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
        finished = call.wait(self.stop)
        end = f.decision.end
        f.result = self.robot_model.checked(call.result(stopped=not finished), end)
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
        """Run robot-side model work and wait for it (where it runs:
        `robotd.frame_path.model_runs`)."""
        return self.runs.run(run, self._pending)

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
        assert call is not None and self.local is not None
        wake = threading.Event()
        call.notify(wake)
        cloud_limit = call.deadline_at + FINISH_GRACE_S
        # The policy may defer the local run (`Decision.hedge_after_s`): a reply within that
        # time serves the frame without any local work competing with the offload.
        start_at = min(call.handed_at + f.decision.hedge_after_s, cloud_limit)
        _wait_until(self.stop, wake, start_at, lambda: call.settled)
        if call.settled and self._served_by_reply(f):
            return
        model, feeds = self.model, f.feeds
        job = self.local.submit(
            self.slowdown.stretched(
                lambda options: model.run_suffix(k, sent, feeds, run_options=options)
            ),
            wake,
        )
        _wait_until(self.stop, wake, cloud_limit, lambda: job.done or call.settled)
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
            self.slowdown.run(
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
            f.result = self.robot_model.checked(call.result())
            replied_at = f.result.replied_at
            if f.result.reply is not None and replied_at is not None and replied_at <= local_done:
                self._serve_cloud(f)
            else:
                f.serve_local(outputs, local_done)
                self._emit(f)
            return
        # The robot's result is first: the frame is served (applied) and handed on now; its
        # reply comes later and completes its telemetry. Held until then, its result reached
        # the consumers late, after the next frame's when that one was answered first.
        f.serve_local(outputs, local_done)
        f.stale = not self._order.admit(f.n)
        if not f.stale:
            self._deliver(f, self._record(f, reply_awaited=True))
        self._settle_pending(block=True)  # at most one frame waits for its reply
        self._pending = f

    def _served_by_reply(self, f: Frame) -> bool:
        """The cloud call of hedged frame `f` has settled: serve and emit the frame with its
        reply if it brought one (True); else keep the result for later (False)."""
        assert f.call is not None
        f.result = self.robot_model.checked(f.call.result())
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
        finished = call.wait(self.stop)
        self._pending = None
        f.result = self.robot_model.checked(call.result(stopped=not finished))
        self._emit(f)

    # -- after a frame ---------------------------------------------------------------------
    def _emit(self, f: Frame) -> None:
        """Feed the policy, publish and record the frame, act on a run of cloud failures, and
        hand an applied frame's result on (`_deliver`) unless that was done when it was served.
        A stale frame (a newer one's result was applied first) is handed to none of them: it is
        counted in its record and the summary."""
        res = f.result
        call = f.call
        if call is not None:
            f.bytes_up = call.bytes_up  # a keyframe resend included
            if call.video is not None and (res is None or res.reply is None):
                self.video.unseen(f.video_at, call.video)  # refused, lost or timed out
        self.policy.observe(f.decision, f.outcome(self.deadline_s))
        if f.stale is None:  # applied now, unless a newer frame's result was
            f.stale = not self._order.admit(f.n)
        record = self._record(f)
        self.sink.frame(f, record, phase=self.emulation.phase_name(f.n))
        self.frames_done += 1
        if res is not None and res.reply is not None:
            self.cloud_time.observe(RemoteTimes.of(res).cloud_s)
        if f.offloaded and res is not None:
            reroute = self._failures.note(f.n, res)
            if reroute is not None:
                self.link.request_reroute(reroute, self._failures.streak)
        if not f.stale and not f.delivered:
            self._deliver(f, record)

    def _record(self, f: Frame, *, reply_awaited: bool = False) -> TelemetryRecord:
        """Frame `f`'s telemetry record; `reply_awaited`: as known while its reply is out."""
        remote = RemoteTimes.of(f.result)
        compute_s = f.prefix_s + (f.local_s or 0.0)
        energy = self.objective.energy_j(f.latency_s, compute_s, remote.transfer_s)
        return f.record(self.robot, energy, reply_awaited=reply_awaited)

    def _deliver(self, f: Frame, record: TelemetryRecord) -> None:
        """Hand applied frame `f`'s result to `on_result`, the result sinks, then the source."""
        f.delivered = True
        result = FrameResult(f.n, f.feeds, f.outputs, record, f.served_by, f.hedged, f.stamp_ns)
        if self.on_result is not None:
            self.on_result(result)
        for sink in self.result_sinks:
            self._publish(sink, result)
        self.source.on_result(result)

    def _publish(self, sink: ResultSink, result: FrameResult) -> None:
        """Hand `result` to `sink`; a sink that fails is a throttled line, never the loop's end."""
        try:
            sink.publish(result)
        except Exception:
            self.throttled.error(
                "%s: result sink %s failed on frame %d",
                self.robot,
                type(sink).__name__,
                result.frame,
                exc_info=True,
            )


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
