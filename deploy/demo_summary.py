"""What a demo run did, from the robot's telemetry: the run's summary, one row per phase, and the
verdict of `--compare` (which policy was fastest in each phase, and whether the demo's policy
chose the action that was).

Everything here is arithmetic on telemetry records (the robot's JSONL objects), so it is tested
without starting anything.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # light at import: `elasticfog --help` imports this module
    from robotd.emulation import Phase

PURE_ROBOT_LABEL = "P"
NEAR_BEST_RATIO = 1.25
"""The demo's policy is `near_best` in a phase when its mean latency is within this factor of the
fastest run's (a learner pays for a few frames of exploration in every phase)."""
ROUND_DIGITS = 6


@dataclass
class Failover:
    """One forced loss of the serving deployment, and how long until another one answered."""

    at_frame: int
    killed: str
    killed_at: float  # wall clock
    to: str | None = None
    ms: float | None = None

    def to_json(self) -> dict[str, Any]:
        ms = None if self.ms is None else round(self.ms, 1)
        return {"at_frame": self.at_frame, "from": self.killed, "to": self.to, "ms": ms}


def read_telemetry(path: Path) -> list[dict[str, Any]]:
    """The robot's `--telemetry` JSONL (one object per frame); a torn last line is skipped."""
    records: list[dict[str, Any]] = []
    if not path.exists():
        return records
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue  # the robot was killed mid-write
        if isinstance(obj, dict):
            records.append(obj)
    return records


def percentile(values: Sequence[float], q: float) -> float | None:
    """Linear-interpolated percentile (numpy's default method), None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    pos = (len(ordered) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def answered_by(record: Mapping[str, Any]) -> str | None:
    """The deployment whose reply served this frame, or None (computed on the robot)."""
    deployment = record.get("deployment")
    if deployment and not record.get("fallback"):
        return str(deployment)
    return None


def answered_since(
    deployment: str, *, from_frame: int = 0, after: float = 0.0
) -> Callable[[Mapping[str, Any]], bool]:
    """A telemetry predicate: a frame answered by `deployment`, from frame `from_frame` on and
    completed at `after` (the record's wall-clock `at`) or later."""

    def answered(record: Mapping[str, Any]) -> bool:
        return (
            answered_by(record) == deployment
            and int(record["frame"]) >= from_frame
            and float(record["at"]) >= after
        )

    return answered


def by_frame(records: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """One record per frame (the first seen), in frame order."""
    frames: dict[int, Mapping[str, Any]] = {}
    for rec in records:
        frame = rec.get("frame")
        if isinstance(frame, int):
            frames.setdefault(frame, rec)
    return [frames[f] for f in sorted(frames)]


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, ROUND_DIGITS)


def _latencies(recs: Iterable[Mapping[str, Any]]) -> list[float]:
    return [float(r["latency_s"]) for r in recs if isinstance(r.get("latency_s"), (int, float))]


def action_order(label: str) -> tuple[int, int, str]:
    """Sort key of action labels: cuts in order (codecs within a cut by name), then P."""
    parts = label.split(":")
    if parts[0] == "cut" and len(parts) > 1 and parts[1].isdigit():
        return (0, int(parts[1]), label)
    return (1, 0, label)


def summarize(
    records: Iterable[dict[str, Any]], frames: int, failovers: Sequence[Failover] = ()
) -> tuple[dict[str, Any], dict[str, int]]:
    """The demo's JSON summary from telemetry records, and the fallback reasons beside it.

    A frame is `answered` when a deployment's reply served it; `fallbacks` are frames the robot
    finished itself after offloading (busy, error, timeout, no route); `lost` are frames asked for
    that have no telemetry record at all (the runtime promises none).
    """
    recs = by_frame(records)
    deployments: Counter[str] = Counter()
    actions: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    fallbacks = 0
    for rec in recs:
        actions[str(rec.get("action"))] += 1
        dep = answered_by(rec)
        if dep is not None:
            deployments[dep] += 1
        if rec.get("fallback"):
            fallbacks += 1
            reasons[str(rec.get("reason") or "unknown")] += 1
    latencies = _latencies(recs)
    seen = sum(1 for r in recs if 0 <= int(r["frame"]) < frames)
    mean = sum(latencies) / len(latencies) if latencies else None
    summary = {
        "frames": frames,
        "answered": sum(deployments.values()),
        "lost": frames - seen,
        "fallbacks": fallbacks,
        "by_deployment": dict(sorted(deployments.items())),
        "actions": dict(sorted(actions.items(), key=lambda kv: action_order(kv[0]))),
        "mean_latency_s": _round(mean),
        "p95_latency_s": _round(percentile(latencies, 95)),
        "failovers": [f.to_json() for f in failovers],
    }
    return summary, dict(reasons.most_common())


def summarize_phases(
    records: Iterable[Mapping[str, Any]], phases: Sequence[Phase]
) -> list[dict[str, Any]]:
    """One row per phase (the `phases` of `--json`): frames are placed by their number, as the
    robot switches phases by frame number.

    `main_action` is the phase's most frequent action (`main_share` of its frames), `bytes_up`
    the mean bytes sent per frame (0 for frames computed on the robot), latencies over every
    frame of the phase, `fallbacks` its frames finished on the robot after offloading."""
    recs = by_frame(records)
    rows = []
    for phase in phases:
        mine = [r for r in recs if phase.first <= int(r["frame"]) < phase.end]
        actions = Counter(str(r.get("action")) for r in mine)
        main, count = actions.most_common(1)[0] if actions else (None, 0)
        latencies = _latencies(mine)
        sent = [int(r.get("bytes_up") or 0) for r in mine]
        rows.append(
            {
                "name": phase.name,
                "frames": phase.frames,
                "uplink_mbit": phase.uplink_mbit,
                "slowdown": phase.slowdown,
                "main_action": main,
                "main_share": round(count / len(mine), 3) if mine else None,
                "actions": dict(sorted(actions.items(), key=lambda kv: action_order(kv[0]))),
                "mean_latency_s": _round(sum(latencies) / len(latencies) if latencies else None),
                "p95_latency_s": _round(percentile(latencies, 95)),
                "bytes_up": round(sum(sent) / len(sent)) if sent else None,
                "fallbacks": sum(1 for r in mine if r.get("fallback")),
            }
        )
    return rows


def complete_failovers(failovers: Sequence[Failover], records: Iterable[dict[str, Any]]) -> None:
    """Fill `to` and `ms` of each failover from telemetry carrying `at` (completion wall clock):
    the first frame completed after the kill and answered by another deployment."""
    ordered = sorted(
        (r for r in records if isinstance(r.get("at"), (int, float))), key=lambda r: r["at"]
    )
    for fo in failovers:
        for rec in ordered:
            dep = answered_by(rec)
            if rec["at"] >= fo.killed_at and dep is not None and dep != fo.killed:
                fo.to = dep
                fo.ms = (float(rec["at"]) - fo.killed_at) * 1000.0
                break


def action_kind(label: str | None) -> str | None:
    """What an action does, for comparing policies: `robot` (P), `offload` (cut 0, any codec:
    the whole frame goes to the cloud) or `cut:<k>` (a middle cut)."""
    if label is None:
        return None
    if label == PURE_ROBOT_LABEL:
        return "robot"
    parts = label.split(":")
    if len(parts) >= 2 and parts[0] == "cut" and parts[1] == "0":
        return "offload"
    return ":".join(parts[:2])


def compare_verdict(runs: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per phase, which run was fastest (lowest mean latency), and whether the first run's
    policy (the demo's, `elastic` by default) got it right: `agrees` when its main action is
    of the same kind as the fastest fixed policy's (`action_kind`), or when it was itself at
    least as fast as every other run (a middle cut that beats both); `near_best` when its mean
    is within `NEAR_BEST_RATIO` of the fastest run's."""
    if not runs:
        return []
    learner, others = runs[0], runs[1:]
    verdict = []
    for i, mine in enumerate(learner["phases"]):
        means = {
            str(run["policy"]): run["phases"][i]["mean_latency_s"]
            for run in runs
            if run["phases"][i]["mean_latency_s"] is not None
        }
        fastest = min(means, key=lambda p: means[p]) if means else None
        fixed = [run for run in others if run["phases"][i]["mean_latency_s"] is not None]
        best_fixed = min(fixed, key=lambda r: r["phases"][i]["mean_latency_s"], default=None)
        own = mine["mean_latency_s"]
        fixed_action = best_fixed["phases"][i]["main_action"] if best_fixed else None
        same_kind = action_kind(mine["main_action"]) == action_kind(fixed_action)
        at_least_as_fast = (
            own is not None
            and best_fixed is not None
            and own <= best_fixed["phases"][i]["mean_latency_s"]
        )
        verdict.append(
            {
                "name": mine["name"],
                "mean_latency_s": means,
                "fastest": fastest,
                "fastest_fixed": None if best_fixed is None else best_fixed["policy"],
                "main_action": mine["main_action"],
                "agrees": bool(same_kind or at_least_as_fast),
                "near_best": (
                    own is not None
                    and fastest is not None
                    and own <= means[fastest] * NEAR_BEST_RATIO
                ),
            }
        )
    return verdict
