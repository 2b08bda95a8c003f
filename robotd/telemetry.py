"""Where a frame's story goes: the `--telemetry` JSONL file, the `tele/<robot>` publication and the
run summary printed at the end.

Each line of the JSONL file is one frame: the contract fields of `common.wire.telemetry`
(`JSONL_FIELDS`: frame, action, bytes_up, bytes_down, prefix_s, transfer_s, cloud_s,
suffix_local_s, latency_s, robot_cpu_s, energy_j, deployment, fallback, reason) followed by
`EXTRA_FIELDS`: `at` (wall clock when the frame completed), `epoch` (the route epoch the robot
knew), `entropy` (the frame's normalized grey-level entropy), `hedged` (the local suffix ran
alongside the cloud), `served_by` (`cloud` or `robot`: which result the frame used), `detail`
(why the cloud failed, for a person: the record's `detail`), `phase` (the emulation phase the
frame ran in, `robotd.emulation`; null without `--phases`), `stale` (the frame's result was
dropped, not applied: a newer frame's had been, `robotd.frame_path.pipeline`), `dropped_stale`
(frames the source dropped unread just before this one: a newer one had arrived,
`robotd.sources.zenoh_in`) and `resends` (how many times the frame's query was sent again within its
deadline, having found no serving deployment: `robotd.frame_path.offload`), `service` (the
service the frame was for: a robot using several writes them all to one file), `keyframe` (a
video frame: whether the frame last sent was a keyframe; null for any other). Lines are flushed
as they are written, so a reader can follow the file while the robot runs.

The record itself is built here too (`frame_record`), from what the frame loop measured and what
came of the cloud call; `RemoteTimes` splits the call's round trip into the network's share and
the deployment's own time, which the record, the energy estimate and the policy's feedback share.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from common.errors import UserError
from common.wire.telemetry import JSONL_FIELDS, TelemetryRecord, action_label, parse_action

if TYPE_CHECKING:  # only read here; importing it would load onnxruntime and zenoh
    from robotd.frame_path.offload import CallResult

EXTRA_FIELDS = (
    "at",
    "epoch",
    "entropy",
    "hedged",
    "served_by",
    "detail",
    "phase",
    "stale",
    "dropped_stale",
    "resends",
    "service",
    "keyframe",
)
SERVED_BY_CLOUD = "cloud"
SERVED_BY_ROBOT = "robot"
P95 = 95.0
ROUND_DIGITS = 6


@dataclass(frozen=True)
class RemoteTimes:
    """How a frame's wait on the cloud splits: `cloud_s` is the deployment's own queue + compute
    time, from its reply (0 without one); `transfer_s` the rest of the round trip (the network
    both ways), or the whole wait when no usable reply came. Both 0 for a frame not offloaded."""

    transfer_s: float = 0.0
    cloud_s: float = 0.0

    @classmethod
    def of(cls, result: CallResult | None) -> RemoteTimes:
        if result is None:
            return cls()
        reply = result.reply
        if reply is None:
            return cls(transfer_s=result.round_trip_s)
        cloud_s = reply.queue_s + reply.compute_s
        return cls(transfer_s=max(0.0, result.round_trip_s - cloud_s), cloud_s=cloud_s)


def frame_record(
    robot: str,
    frame: int,
    *,
    cut: int | None,
    codec: str,
    result: CallResult | None,
    bytes_up: int,
    prefix_s: float,
    local_s: float | None,
    latency_s: float,
    cpu_s: float,
    energy_j: float,
    epoch: int,
    stale: bool = False,
    end: int | None = None,
    dropped_stale: int = 0,
    reply_awaited: bool = False,
    keyframe: bool | None = None,
) -> TelemetryRecord:
    """The telemetry record of a completed frame.

    `cut` None: the whole model ran on the robot (P). Otherwise `result` is what came of the
    cloud call; an offloaded frame without a reply is a fallback, with the result's reason and
    its detail.
    `end`: the segment's end cut (the action is `cut:<k>-<end>`), for a segment offload.
    `local_s`: the robot's own suffix run, if one ran. `epoch`: the route epoch the robot held
    when the frame started; an answered frame reports its reply's instead. `stale`: its result
    was dropped, a newer frame's having been applied. `dropped_stale`: frames the source
    dropped unread just before this one. `keyframe`: a video frame's kind (None for others).
    `reply_awaited`: the record of a hedged frame that the
    robot served while its reply was still out, for its consumers: not a fallback (the robot's
    run won the race; whether the cloud answers is not known yet) and no reply's figures.
    """
    reply = result.reply if result is not None else None
    fallback = cut is not None and reply is None and not reply_awaited
    remote = RemoteTimes.of(result)
    return TelemetryRecord(
        robot=robot,
        frame=frame,
        action=action_label(cut, codec, end),
        bytes_up=bytes_up,
        bytes_down=result.bytes_down if result is not None else 0,
        prefix_s=prefix_s,
        transfer_s=remote.transfer_s,
        cloud_s=remote.cloud_s,
        suffix_local_s=local_s or 0.0,
        latency_s=latency_s,
        robot_cpu_s=cpu_s,
        energy_j=float(energy_j),
        deployment=result.deployment if result is not None else None,
        fallback=fallback,
        reason=result.reason if fallback and result is not None else None,
        detail=(result.detail or None) if fallback and result is not None else None,
        epoch=reply.epoch if reply is not None else epoch,
        at=time.time(),
        stale=stale,
        dropped_stale=dropped_stale,
        resends=len(result.resends) if result is not None else 0,
        keyframe=keyframe,
    )


def jsonl_object(
    record: TelemetryRecord,
    *,
    entropy: float,
    hedged: bool,
    served_by: str,
    phase: str | None = None,
) -> dict[str, Any]:
    """The JSONL object of one frame (contract fields first, then EXTRA_FIELDS)."""
    obj = record.to_jsonl()
    obj.update(
        at=record.at,
        epoch=record.epoch,
        entropy=round(entropy, ROUND_DIGITS),
        hedged=hedged,
        served_by=served_by,
        detail=record.detail or None,
        phase=phase,
        stale=record.stale,
        dropped_stale=record.dropped_stale,
        resends=record.resends,
        service=record.service,
        keyframe=record.keyframe,
    )
    return obj


class TelemetryFile:
    """The `--telemetry` JSONL file (truncated at open: one run per file); a context manager
    that closes it. The frame loops of a robot's services write it from their own threads: a
    lock keeps each line whole."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[str] | None = self.path.open("w", encoding="utf-8")
        except OSError as exc:
            raise UserError(f"--telemetry {self.path}: cannot write: {exc.strerror}") from None

    def write(self, obj: dict[str, Any]) -> None:
        line = json.dumps(obj, allow_nan=False, separators=(",", ":")) + "\n"
        with self._lock:
            if self._file is None:
                return
            self._file.write(line)
            self._file.flush()

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None

    def __enter__(self) -> TelemetryFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunSummary:
    """Counts over the run's frames, for the summary printed at the end."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.frames = 0
        self.answered = 0
        self.fallbacks = 0
        self.hedged = 0
        self.served_by_robot = 0
        self.stale_dropped = 0
        self.resends = 0  # queries sent again within their frame's deadline, over all frames
        # Frames the source dropped unread (a newer one arrived first), and frames it could not
        # decode by error code: set from the source when the run ends.
        self.dropped_stale = 0
        self.rejected_frames: dict[str, int] = {}
        self.reasons: Counter[str] = Counter()
        self.by_deployment: Counter[str] = Counter()
        self.actions: Counter[str] = Counter()
        self.latencies: list[float] = []
        self.started_at: float | None = None
        self.ended_at: float | None = None

    def add(self, record: TelemetryRecord, *, hedged: bool, served_by: str) -> None:
        self.frames += 1
        self.actions[record.action] += 1
        if record.deployment is not None and not record.fallback:
            self.answered += 1
            self.by_deployment[record.deployment] += 1
        if record.fallback:
            self.fallbacks += 1
            self.reasons[record.reason.value if record.reason is not None else "unknown"] += 1
        if hedged:
            self.hedged += 1
        if served_by == SERVED_BY_ROBOT:
            self.served_by_robot += 1
        if record.stale:
            self.stale_dropped += 1
        self.resends += record.resends
        if math.isfinite(record.latency_s):
            self.latencies.append(record.latency_s)

    def to_json(self) -> dict[str, Any]:
        """`{robot, frames, answered, fallbacks, fallback_reasons, by_deployment, actions, hedged,
        served_by_robot, stale_dropped, dropped_stale, rejected_frames, resends, mean_latency_s,
        p95_latency_s, fps}`."""
        lat = np.asarray(self.latencies, dtype=np.float64)
        mean = float(lat.mean()) if lat.size else None
        p95 = float(np.percentile(lat, P95)) if lat.size else None
        duration = (
            self.ended_at - self.started_at
            if self.started_at is not None and self.ended_at is not None
            else None
        )
        fps = self.frames / duration if duration and duration > 0 else None
        return {
            "robot": self.robot,
            "frames": self.frames,
            "answered": self.answered,
            "fallbacks": self.fallbacks,
            "fallback_reasons": dict(self.reasons.most_common()),
            "by_deployment": dict(sorted(self.by_deployment.items())),
            "actions": dict(sorted(self.actions.items(), key=lambda kv: _action_key(kv[0]))),
            "hedged": self.hedged,
            "served_by_robot": self.served_by_robot,
            "stale_dropped": self.stale_dropped,
            "dropped_stale": self.dropped_stale,
            "rejected_frames": dict(sorted(self.rejected_frames.items())),
            "resends": self.resends,
            "mean_latency_s": _round(mean),
            "p95_latency_s": _round(p95),
            "fps": _round(fps),
        }

    def lines(self) -> list[str]:
        """The summary for a person, a few lines."""
        s = self.to_json()

        def ms(value: float | None) -> str:
            return "n/a" if value is None else f"{value * 1000:.1f} ms"

        reasons = ", ".join(f"{k} {v}" for k, v in s["fallback_reasons"].items()) or "none"
        deployments = ", ".join(f"{k} {v}" for k, v in s["by_deployment"].items()) or "none"
        actions = ", ".join(f"{k} {v}" for k, v in s["actions"].items()) or "none"
        rate = "" if s["fps"] is None else f" ({s['fps']:.1f} frames/s)"
        return [
            f"{self.robot}: {s['frames']} frames{rate}",
            f"  answered by the cloud: {s['answered']} ({deployments})",
            f"  finished on the robot after offloading: {s['fallbacks']} ({reasons})",
            f"  hedged: {s['hedged']}, served by the robot's own result: {s['served_by_robot']}",
            f"  stale results dropped (a newer frame's applied first): {s['stale_dropped']}",
            f"  stale frames dropped unread (a newer one arrived first): {s['dropped_stale']}",
            *(
                [f"  frames rejected: {_counts(s['rejected_frames'])}"]
                if s["rejected_frames"]
                else []
            ),
            *(
                [f"  queries resent (no serving deployment found): {s['resends']}"]
                if s["resends"]
                else []
            ),
            f"  actions: {actions}",
            f"  latency: mean {ms(s['mean_latency_s'])}, p95 {ms(s['p95_latency_s'])}",
        ]


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items())


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, ROUND_DIGITS)


def _action_key(label: str) -> tuple[int, int]:
    cut = parse_action(label)
    return (1, 0) if cut is None else (0, cut)


__all__ = [
    "EXTRA_FIELDS",
    "JSONL_FIELDS",
    "SERVED_BY_CLOUD",
    "SERVED_BY_ROBOT",
    "RemoteTimes",
    "RunSummary",
    "TelemetryFile",
    "frame_record",
    "jsonl_object",
]
