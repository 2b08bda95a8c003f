"""Figures from a robot's telemetry records (its `--telemetry` JSONL, one object per frame).

Every experiment reduces records the same way: a window of frames gives mean/median/p95
latency, robot CPU seconds and energy per frame, bytes sent, the actions taken and the fallbacks;
a change (a bandwidth glitch, a CPU quota drop) splits a run into before / on / after, where
"on" lasts until the policy settles; frames asked for but never reported are lost.
"""

from __future__ import annotations

import statistics
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from common.wire.telemetry import parse_action

Record = dict[str, Any]

SETTLE_WINDOW_FRAMES = 10
"""A policy has settled once this many frames in a row mostly take its final action."""
SETTLE_FRACTION = 0.8
"""...that is, at least this fraction of them (exploration frames may interleave)."""
ON_MIN_FRAMES = 3
"""The "on" phase lasts at least this many frames (a fixed policy settles at once, but the
requests queued at the old rate still drain at the new one)."""


def by_frame(records: Iterable[Record]) -> list[Record]:
    """One record per frame (the first one seen), in frame order."""
    seen: dict[int, Record] = {}
    for rec in records:
        frame = rec.get("frame")
        if isinstance(frame, int) and frame not in seen:
            seen[frame] = rec
    return [seen[f] for f in sorted(seen)]


def lost_frames(records: Iterable[Record], frames: int) -> list[int]:
    """Frames in 0..frames-1 without a record (the runtime promises none)."""
    seen = {rec.get("frame") for rec in records}
    return [f for f in range(frames) if f not in seen]


def between(records: Sequence[Record], start: int, stop: int | None = None) -> list[Record]:
    """Records of frames start <= frame < stop."""
    return [r for r in records if r["frame"] >= start and (stop is None or r["frame"] < stop)]


def percentile(values: Sequence[float], q: float) -> float | None:
    """Linear-interpolated percentile (numpy's default), None without values."""
    if not values:
        return None
    ordered = sorted(values)
    pos = (len(ordered) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


@dataclass(frozen=True)
class WindowSummary:
    """Per-frame figures of a window of records (`summary`); None where the window is empty.
    The fields, in order, are the keys of its JSON object (`to_json`)."""

    frames: int
    mean_latency_s: float | None
    median_latency_s: float | None
    p95_latency_s: float | None
    robot_cpu_s: float | None
    energy_j: float | None
    bytes_up: float | None
    fallbacks: int
    actions: dict[str, int]
    """Frames per action, most frequent first."""
    main_action: str | None
    deployments: dict[str, int]
    """Offloaded frames per deployment that answered, most frequent first."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def summary(records: Sequence[Record]) -> WindowSummary:
    """Per-frame figures of a window of records."""
    latency = [float(r["latency_s"]) for r in records]
    actions = Counter(str(r["action"]) for r in records)
    deployments = Counter(str(r["deployment"]) for r in records if r.get("deployment"))
    return WindowSummary(
        frames=len(records),
        mean_latency_s=_mean(latency),
        median_latency_s=statistics.median(latency) if latency else None,
        p95_latency_s=percentile(latency, 95),
        robot_cpu_s=_mean([float(r["robot_cpu_s"]) for r in records]),
        energy_j=_mean([float(r["energy_j"]) for r in records]),
        bytes_up=_mean([float(r["bytes_up"]) for r in records]),
        fallbacks=sum(1 for r in records if r.get("fallback")),
        actions=dict(actions.most_common()),
        main_action=actions.most_common(1)[0][0] if actions else None,
        deployments=dict(deployments.most_common()),
    )


def action_order(label: str) -> int:
    """Where an action sits between full offload (cut 0) and pure robot (largest)."""
    cut = parse_action(label)
    return 1 << 30 if cut is None else cut


def final_action(records: Sequence[Record]) -> str | None:
    """The action a policy ended on: the most frequent one over the last third of `records`."""
    if not records:
        return None
    tail = records[len(records) - max(1, len(records) // 3) :]
    return Counter(str(r["action"]) for r in tail).most_common(1)[0][0]


def settle_frames(
    records: Sequence[Record],
    change_frame: int,
    *,
    window: int = SETTLE_WINDOW_FRAMES,
    fraction: float = SETTLE_FRACTION,
) -> int | None:
    """Frames from the change until the policy settles on its final action.

    The final action is the most frequent one over the last third of the frames after the
    change; the policy has settled at the first frame that takes it and from which at least
    `fraction` of the next `window` frames take it (exploration frames may interleave).
    0: it never left it. None: it never settled (too few frames)."""
    after = [r for r in records if r["frame"] >= change_frame]
    target = final_action(after)
    if target is None:
        return None
    need = max(1, round(fraction * min(window, len(after))))
    for i in range(len(after)):
        chunk = after[i : i + window]
        if len(chunk) < min(window, len(after)):
            break
        if chunk[0]["action"] == target and sum(1 for r in chunk if r["action"] == target) >= need:
            return int(after[i]["frame"]) - change_frame
    return None


@dataclass(frozen=True)
class Phases:
    """A run split by a change (`phases`): the frames the policy took to settle (None: it never
    did), and the windows before, on and after the change."""

    settle_frames: int | None
    before: WindowSummary
    on: WindowSummary
    after: WindowSummary


def phases(
    records: Sequence[Record], start: int, change_frame: int, stop: int | None = None
) -> Phases:
    """Before / on / after a change at `change_frame` (frames from `start`, up to `stop`).

    "on" runs from the change until the policy settles (at least ON_MIN_FRAMES frames),
    "after" from there on."""
    window = between(records, start, stop)
    settle = settle_frames(between(window, change_frame), change_frame)
    on_frames = max(ON_MIN_FRAMES, settle if settle is not None else 0)
    settled_at = change_frame + on_frames
    return Phases(
        settle_frames=settle,
        before=summary(between(window, start, change_frame)),
        on=summary(between(window, change_frame, settled_at)),
        after=summary(between(window, settled_at)),
    )
