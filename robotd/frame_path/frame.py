"""One frame on its way through the robot's frame loop, and what it hands on once served.

The loop fills a `Frame` as the frame advances (prefix time, bytes sent, the cloud call and its
result, the robot's own suffix run, the outputs that served it). Once served, the frame gives
the policy its `Outcome` (what the offload cost, or that the cloud did not answer) and the
telemetry its record (`robotd.telemetry.frame_record`); embedders get a `FrameResult`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from common.wire.telemetry import FallbackReason, TelemetryRecord
from robotd.frame_path.offload import CallResult, CloudCall
from robotd.policies import PURE_ROBOT, Decision, Outcome
from robotd.telemetry import SERVED_BY_CLOUD, SERVED_BY_ROBOT, RemoteTimes, frame_record


@dataclass(frozen=True)
class FrameResult:
    """An applied frame, handed to `on_result`: its input, its outputs (whichever path served
    it) and its telemetry record as known then (a hedged frame the robot served while its reply
    was out is handed on at once: its record has no reply's figures and is no fallback; the
    telemetry gets the complete record when the reply settles)."""

    frame: int
    feeds: dict[str, np.ndarray]
    outputs: dict[str, np.ndarray]
    record: TelemetryRecord
    served_by: str
    hedged: bool
    # When the frame was captured (ns since the epoch): the source's stamp, else when it was read.
    stamp_ns: int = 0


@dataclass
class Frame:
    """One frame on its way through the loop. Times are `time.perf_counter` seconds, CPU times
    `time.process_time` seconds; `epoch` is the route epoch held when the frame started."""

    n: int
    decision: Decision
    entropy: float
    feeds: dict[str, np.ndarray]
    started: float
    cpu_started: float
    epoch: int
    # Capture stamp, ns since the epoch (`FrameSource.last_stamp_ns`, else the read time).
    stamp_ns: int = 0
    prefix_s: float = 0.0
    local_s: float | None = None
    bytes_up: int = 0
    call: CloudCall | None = None
    result: CallResult | None = None
    outputs: dict[str, np.ndarray] = field(default_factory=dict)
    served_by: str = SERVED_BY_ROBOT
    latency_s: float = 0.0
    cpu_s: float = 0.0
    # Whether the frame's result was dropped (a newer frame's was applied first,
    # `robotd.frame_path.pipeline.ResultOrder`); None until it is applied or dropped.
    stale: bool | None = None
    # Frames the source dropped unread just before this one (a newer one had arrived).
    dropped_stale: int = 0
    # Its result was handed to the consumers (a hedged frame served by the robot is handed on
    # when served, before its reply completes its record).
    delivered: bool = False
    # A video frame (`h264`): the deployment whose stream it was coded in
    # (`robotd.frame_path.video_streams`; "" when no route was known).
    video_at: str | None = None

    @property
    def keyframe(self) -> bool | None:
        """A video frame: whether the frame last sent for it was a keyframe; None otherwise."""
        video = self.call.video if self.call is not None else None
        return None if video is None else video.keyframe

    @property
    def offloaded(self) -> bool:
        """Sent to the cloud (any cut, not P)."""
        return self.decision.action != PURE_ROBOT

    @property
    def hedged(self) -> bool:
        """Offloaded and raced against the robot's own suffix run."""
        return self.decision.hedge and self.offloaded

    def serve_local(self, outputs: dict[str, np.ndarray], done_at: float) -> None:
        """Serve the frame with the robot's own result, finished at `done_at`."""
        self.outputs, self.latency_s = outputs, done_at - self.started
        self.cpu_s = time.process_time() - self.cpu_started

    def serve_cloud(self, result: CallResult) -> None:
        """Serve the frame with the cloud's reply in `result`."""
        assert result.reply is not None and result.replied_at is not None
        self.outputs = dict(result.reply.outputs)
        self.served_by = SERVED_BY_CLOUD
        self.latency_s = result.replied_at - self.started
        self.cpu_s = time.process_time() - self.cpu_started

    def outcome(self, deadline_s: float) -> Outcome:
        """What the policy learns from the served frame. Without a reply the robot waited
        `deadline_s` for the cloud (or less, when it failed early) and finished the frame."""
        if not self.offloaded:
            return Outcome(prefix_s=self.prefix_s, latency_s=self.latency_s)
        res = self.result
        answered = res is not None and res.reply is not None
        return Outcome(
            prefix_s=self.prefix_s,
            cloud_s=res.round_trip_s if res is not None and answered else None,
            cloud_compute_s=RemoteTimes.of(res).cloud_s if answered else None,
            bytes_up=self.bytes_up,
            local_s=self.local_s,
            latency_s=self.latency_s,
            waited_s=None if answered else deadline_s,
            timed_out=res is not None and res.reason is FallbackReason.TIMEOUT,
            cpu_s=self.cpu_s,
            keyframe=self.keyframe,
        )

    def record(
        self, robot: str, energy_j: float, *, reply_awaited: bool = False
    ) -> TelemetryRecord:
        """The served frame's telemetry record; `reply_awaited`: as known while its reply is out
        (see `frame_record`)."""
        return frame_record(
            robot,
            self.n,
            cut=int(self.decision.action) if self.offloaded else None,
            codec=self.decision.codec,
            end=self.decision.end,
            result=self.result,
            bytes_up=self.bytes_up,
            prefix_s=self.prefix_s,
            local_s=self.local_s,
            latency_s=self.latency_s,
            cpu_s=self.cpu_s,
            energy_j=energy_j,
            epoch=self.epoch,
            stale=bool(self.stale),
            dropped_stale=self.dropped_stale,
            reply_awaited=reply_awaited,
            keyframe=self.keyframe,
        )
