"""Trace-driven simulator: replays a trace against a policy with a model's real profile.

Cost model, per segment (times in seconds; the profile was taken on some host):
- robot time of a prefix/suffix/whole model = profiled time / robot_cpu;
- uplink = bytes·8 / uplink + rtt/2; cloud compute = suffix time / cloud_speedup;
  downlink = returned bytes·8 / downlink + rtt/2 (the model's outputs; a segment's end-cut
  tensors, `CutTable.returns`); y = uplink + cloud + downlink;
- every one of robot, uplink, cloud and downlink time is multiplied per frame by its own seeded
  lognormal factor of mean 1 (σ = `noise.jitter`). The factors are drawn once per frame from the
  seed, independent of the policy, so every policy (and the oracle) meets the same conditions.
- an offloaded frame costs prefix + y; a hedged one prefix + min(y, d + local suffix), its local
  suffix starting d (the decision's `hedge_after_s`) after the request and stopped when the reply
  comes first (it then reports no robot time); with a `deadline_ms`, a reply later than the
  deadline is lost and the robot finishes locally after waiting (a hedged frame's local run then
  started at d or at the deadline, whichever is first). Frames are independent (no queueing).
- a segment (cut_in → cut_out) is never hedged; its robot part is the prefix and, after the
  reply, the tail; a reply past the deadline is finished from cut_in, without the tail.

- a video action (`h264`) sends a keyframe (`CutTable.keys` bytes) on its first frame and on the
  first after any frame it did not serve from the cloud (another action, P, or no reply in time),
  a P-frame (`CutTable.bytes`) otherwise, as the robot's streams do
  (`robotd.frame_path.video_streams`); the policy is told which (`FrameContext.keyframe`).

The expected cost of an action is its cost at the mean conditions of its segment (a video
action's, at its P-frames' bytes: a keyframe frame's served cost is at its keyframe's). The oracle
picks the least expected cost in every segment; regret sums, frame by frame, the expected cost of
what the policy served (a hedged frame: its faster path) minus the oracle's.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import UserError
from common.wire.tensor_codecs import is_video
from robotd.policies import make_policy
from robotd.policies.base import (
    BYTES_PER_MB,
    PURE_ROBOT,
    CutTable,
    FloatArray,
    FrameContext,
    Outcome,
)
from robotd.policies.objective import Objective
from robotd.policies.segment_actions import actions_table
from robotd.sim.trace import ConstantEntropy, Segment, Trace, UniformEntropy, video_entropies

BITS_PER_BYTE = 8.0
MBIT = 1e6
MS_PER_S = 1000.0
# A frame is "near the oracle" when its expected cost is within this factor of the oracle's.
SETTLE_TOLERANCE = 1.05
SETTLE_WINDOW_FRAMES = 20
SETTLE_FRACTION = 0.9
REGRET_CURVE_POINTS = 200


@dataclass(frozen=True)
class SegmentCosts:
    """Mean-condition times and expected costs of every action in one segment."""

    prefix_s: FloatArray  # robot time of each prefix
    local_s: FloatArray  # robot time of each suffix
    full_s: float  # robot time of the whole model
    uplink_s: FloatArray
    compute_s: FloatArray  # cloud compute of each suffix
    downlink_s: FloatArray  # of each action's reply
    head_s: FloatArray  # robot time before the reply (a segment's prefix without its tail)
    plain: FloatArray  # expected cost of each action, cuts then P, served as decided
    hedged: FloatArray  # expected cost of each cut when hedged (P: same as plain)
    latency_plain: FloatArray  # expected latency of each action
    oracle: int  # column of the least expected cost

    @property
    def oracle_cost(self) -> float:
        """The oracle's expected cost."""
        return float(self.plain[self.oracle])


def segment_costs(
    cuts: CutTable, seg: Segment, objective: Objective, deadline_s: float | None
) -> SegmentCosts:
    """Times and expected costs of every action under a segment's mean conditions."""
    prefix = cuts.prefix_s / seg.robot_cpu
    local = cuts.suffix_s / seg.robot_cpu
    full = cuts.full_s / seg.robot_cpu
    uplink = cuts.bytes * BITS_PER_BYTE / (seg.uplink_mbit * MBIT) + seg.rtt_ms / MS_PER_S / 2
    compute = cuts.cloud_s / seg.cloud_speedup
    downlink = (
        cuts.returned_bytes * BITS_PER_BYTE / (seg.downlink_mbit * MBIT) + seg.rtt_ms / MS_PER_S / 2
    )
    head = (cuts.prefix_s - cuts.tail_s) / seg.robot_cpu
    segment = np.array([e is not None for e in cuts.ends], dtype=bool)
    y = uplink + compute + downlink
    mb = cuts.bytes / BYTES_PER_MB
    radio = y - compute
    if deadline_s is None:
        answered = np.ones(cuts.size, dtype=bool)
    else:
        answered = y <= deadline_s
        radio = np.where(answered, radio, np.minimum(radio, deadline_s))
    wait = y if deadline_s is None else np.where(answered, y, deadline_s)
    lat_plain = np.where(answered, prefix + y, head + wait + local)
    cpu_plain = np.where(answered, prefix, head + local)
    lat_hedged = np.where(answered, prefix + np.minimum(y, local), prefix + local)
    # A local run that loses to the reply is stopped then.
    cpu_hedged = prefix + np.where(answered, np.minimum(y, local), local)
    plain = objective.frame_cost(lat_plain, cpu_plain, radio, mb)
    # A segment is not hedged: its "hedged" cost is its plain one.
    hedged = np.where(segment, plain, objective.frame_cost(lat_hedged, cpu_hedged, radio, mb))
    p_cost = objective.frame_cost(full, full, 0.0, 0.0)
    plain_all = np.append(plain, p_cost)
    return SegmentCosts(
        prefix_s=prefix,
        local_s=local,
        full_s=full,
        uplink_s=uplink,
        compute_s=compute,
        downlink_s=downlink,
        head_s=head,
        plain=plain_all,
        hedged=np.append(hedged, p_cost),
        latency_plain=np.append(lat_plain, full),
        oracle=int(np.argmin(plain_all)),
    )


@dataclass
class SimResult:
    """Everything a run produced, frame by frame."""

    policy: str
    frames_per_second: float
    segment_starts: list[int]
    segment_names: list[str | None]
    actions: tuple[str, ...]  # labels of the action columns, cuts then P
    column: np.ndarray  # action column served per frame
    hedged: np.ndarray  # bool per frame
    latency_s: FloatArray
    served_cost: FloatArray  # expected cost of what was served
    oracle_cost: FloatArray  # the oracle's expected cost
    oracle_latency_s: FloatArray
    decision_ns: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        """Number of frames replayed."""
        return int(self.latency_s.size)

    def regret(self) -> FloatArray:
        """Cumulative regret R(t) after t = 1..frames frames (objective units)."""
        return np.cumsum(self.served_cost - self.oracle_cost)

    def near_oracle(self) -> np.ndarray:
        """Per frame: served at an expected cost within 5% of the oracle's."""
        return self.served_cost <= SETTLE_TOLERANCE * self.oracle_cost + 1e-12

    def segment_bounds(self) -> list[tuple[int, int]]:
        """(first, end) frame of every segment."""
        ends = [*self.segment_starts[1:], self.frames]
        return list(zip(self.segment_starts, ends, strict=True))

    def settle_frames(self) -> list[int | None]:
        """Frames from each segment's start until it settled (None: never).

        Settled at offset s when frame s is near the oracle and at least 90% of the 20 frames
        from s on are: the first frame of the first good window that starts with a good frame.
        """
        good = self.near_oracle()
        settles: list[int | None] = []
        for first, end in self.segment_bounds():
            seg = good[first:end].astype(np.int64)
            n_windows = seg.size - SETTLE_WINDOW_FRAMES + 1
            if n_windows <= 0:
                settles.append(None)
                continue
            sums = np.convolve(seg, np.ones(SETTLE_WINDOW_FRAMES, dtype=np.int64), "valid")
            need = math.ceil(SETTLE_FRACTION * SETTLE_WINDOW_FRAMES - 1e-9)
            ok = (sums >= need) & (seg[:n_windows] == 1)
            hits = np.flatnonzero(ok)
            settles.append(int(hits[0]) if hits.size else None)
        return settles

    def summary(self) -> dict[str, Any]:
        """The `elasticfog sim --json` document (contract)."""
        regret = self.regret()
        mean = float(self.latency_s.mean())
        oracle_mean = float(self.oracle_latency_s.mean())
        counts = np.bincount(self.column, minlength=len(self.actions))
        points = np.unique(
            np.linspace(1, self.frames, min(REGRET_CURVE_POINTS, self.frames)).round().astype(int)
        )
        segments = []
        for i, ((first, end), settle) in enumerate(
            zip(self.segment_bounds(), self.settle_frames(), strict=True)
        ):
            segments.append(
                {
                    "index": i,
                    "mean_latency_s": _r(float(self.latency_s[first:end].mean())),
                    "oracle_mean_latency_s": _r(float(self.oracle_latency_s[first:end].mean())),
                    "settle_frames": settle,
                }
            )
        return {
            "policy": self.policy,
            "frames": self.frames,
            "mean_latency_s": _r(mean),
            "p95_latency_s": _r(float(np.percentile(self.latency_s, 95))),
            "oracle_mean_latency_s": _r(oracle_mean),
            "ratio_to_oracle": _r(mean / oracle_mean if oracle_mean > 0 else math.inf),
            "cumulative_regret": _r(float(regret[-1])),
            "regret_curve": [[int(t), _r(float(regret[t - 1]))] for t in points],
            "segments": segments,
            "actions": {
                self.actions[c]: int(counts[c]) for c in range(len(self.actions)) if counts[c]
            },
            "decision_us_median": _r(float(np.median(self.decision_ns)) / 1000.0, 3),
        }


def _r(value: float, digits: int = 6) -> float:
    return round(value, digits) if math.isfinite(value) else value


def regret_slope(result: SimResult, first: int = 1000, last: int | None = None) -> float:
    """Least-squares slope of log R(t) against log t over t in [first, last].

    1 means linear regret (a constant fraction of frames is wasted), below 1 sublinear; a regret
    that stays at or below zero over the range counts as 0 (nothing left to learn).
    """
    regret = result.regret()
    last = result.frames if last is None else min(last, result.frames)
    if first < 1 or last <= first:
        raise ValueError("regret_slope needs 1 <= first < last <= frames")
    t = np.unique(np.geomspace(first, last, 64).round().astype(int))
    r = regret[t - 1]
    if np.all(r <= 0):
        return 0.0
    keep = r > 0
    if keep.sum() < 2:
        return 0.0
    slope, _ = np.polyfit(np.log(t[keep]), np.log(r[keep]), 1)
    return float(slope)


class Simulator:
    """Replays one trace with one profile; `run(policy)` for each policy to compare."""

    def __init__(
        self,
        cuts: CutTable,
        trace: Trace,
        *,
        seed: int = 0,
        objective: Objective | Mapping[str, Any] | None = None,
        trace_dir: Path | None = None,
    ) -> None:
        self.cuts = cuts
        self.trace = trace
        self.seed = seed
        self.objective = Objective.parse(objective)
        self.deadline_s = None if trace.deadline_ms is None else trace.deadline_ms / MS_PER_S
        self.segments = [
            segment_costs(cuts, seg, self.objective, self.deadline_s) for seg in trace.segments
        ]
        # A video action's keyframe: the same action sending its keyframe's bytes.
        self.video = [j for j, codec in enumerate(cuts.codecs) if is_video(codec)]
        keyed = dataclasses.replace(cuts, bytes=np.array(cuts.keys, dtype=np.float64))
        self.key_segments = [
            segment_costs(keyed, seg, self.objective, self.deadline_s) for seg in trace.segments
        ]
        total = trace.total_frames
        self.segment_of = np.repeat(
            np.arange(len(trace.segments)), [s.frames for s in trace.segments]
        )
        rng = np.random.default_rng(seed)
        sigma = trace.noise.jitter
        # Mean-one lognormal factors for robot, uplink, cloud, downlink times (common to policies).
        self.factors = rng.lognormal(mean=-(sigma**2) / 2, sigma=sigma, size=(4, total))
        self.entropy = self._entropies(rng, total, trace_dir)
        self._oracle_latency = self._oracle_latencies()

    def _entropies(
        self, rng: np.random.Generator, total: int, trace_dir: Path | None
    ) -> FloatArray:
        source = self.trace.entropy
        if isinstance(source, UniformEntropy):
            return rng.uniform(source.low, source.high, size=total)
        if isinstance(source, ConstantEntropy):
            return np.full(total, source.value)
        path = Path(source.path)
        if not path.is_absolute() and trace_dir is not None:
            path = trace_dir / path
        return video_entropies(path, total)

    def _delayed_hedge_cost(self, table: tuple[Any, ...], j: int, after_s: float) -> float:
        """Expected cost of cut j hedged with its local run starting `after_s` after the request
        (the segment's mean conditions; `table` is the run's per-segment table)."""
        prefix, local, _full, uplink, compute, downlink = table[:6]
        y = uplink[j] + compute[j] + downlink[j]
        deadline = self.deadline_s
        if deadline is None or y <= deadline:
            done = min(y, after_s + local[j])
            lat, ran, radio = prefix[j] + done, max(0.0, done - after_s), y - compute[j]
        else:
            lat = prefix[j] + min(after_s, deadline) + local[j]
            ran, radio = local[j], min(y - compute[j], deadline)
        mb = float(self.cuts.bytes[j]) / BYTES_PER_MB
        return float(self.objective.frame_cost(lat, prefix[j] + ran, radio, mb))

    def _realized(self, seg: SegmentCosts, col: int, frames: slice) -> FloatArray:
        """Realized latency of always serving column `col` (unhedged) over `frames`."""
        fr, fu, fc, fd = (f[frames] for f in self.factors)
        if col == self.cuts.size:
            return seg.full_s * fr
        y = seg.uplink_s[col] * fu + seg.compute_s[col] * fc + seg.downlink_s[col] * fd
        prefix = seg.prefix_s[col] * fr
        if self.deadline_s is None:
            return prefix + y
        late = (seg.head_s[col] + seg.local_s[col]) * fr + self.deadline_s
        return np.where(y <= self.deadline_s, prefix + y, late)

    def _oracle_latencies(self) -> FloatArray:
        out = np.empty(self.trace.total_frames)
        for seg, (first, end) in zip(self.segments, self._bounds(), strict=True):
            out[first:end] = self._realized(seg, seg.oracle, slice(first, end))
        return out

    def _bounds(self) -> list[tuple[int, int]]:
        starts = self.trace.segment_starts
        return list(zip(starts, [*starts[1:], self.trace.total_frames], strict=True))

    def run(
        self, spec: str, params: Mapping[str, Any] | None = None, *, label: str | None = None
    ) -> SimResult:
        """Replay the whole trace against a fresh policy built from `spec`."""
        policy = make_policy(spec, self.cuts, params, self.objective)
        cuts = self.cuts
        k = cuts.size
        total = self.trace.total_frames
        position = cuts.positions()
        bytes_up = [int(b) for b in cuts.bytes]
        key_bytes_up = [int(b) for b in cuts.keys]
        video = set(self.video)
        stream_whole = False  # a video action's next frame is a P-frame
        key_tables = [
            (seg.uplink_s.tolist(), seg.plain.tolist(), seg.hedged.tolist())
            for seg in self.key_segments
        ]
        # Python lists: scalar reads from lists are several times cheaper than from arrays.
        tables = [
            (
                seg.prefix_s.tolist(),
                seg.local_s.tolist(),
                seg.full_s,
                seg.uplink_s.tolist(),
                seg.compute_s.tolist(),
                seg.downlink_s.tolist(),
                seg.plain.tolist(),
                seg.hedged.tolist(),
                tuple(seg.plain.tolist()),
                seg.head_s.tolist(),
            )
            for seg in self.segments
        ]
        fr_all, fu_all, fc_all, fd_all = (f.tolist() for f in self.factors)
        entropy = self.entropy.tolist()
        segment_of = self.segment_of.tolist()
        deadline = self.deadline_s
        column = np.empty(total, dtype=np.int64)
        hedged = np.zeros(total, dtype=bool)
        latency = np.empty(total)
        served = np.empty(total)
        decision_ns = np.empty(total, dtype=np.int64)
        clock = time.perf_counter_ns
        for t in range(total):
            s = segment_of[t]
            table = tables[s]
            prefix, local, full, uplink, compute, downlink, plain, hedge_cost, truth, head = table
            keyframe = bool(video) and not stream_whole
            ctx = FrameContext(index=t, entropy=entropy[t], expected_costs=truth, keyframe=keyframe)
            started = clock()
            decision = policy.decide(ctx)
            decision_ns[t] = clock() - started
            fr = fr_all[t]
            if decision.action == PURE_ROBOT:
                j = k
                lat = full * fr
                outcome = Outcome(prefix_s=lat, latency_s=lat)
                cost = plain[k]
                stream_whole = False
            else:
                j = position[(int(decision.action), decision.codec, decision.end)]
                sent = bytes_up[j]
                is_key: bool | None = None
                if j in video:
                    is_key = keyframe
                    if keyframe:  # its keyframe's uplink and costs
                        uplink, plain, hedge_cost = key_tables[s]
                        sent = key_bytes_up[j]
                pre = prefix[j] * fr
                cc = compute[j] * fc_all[t]
                y = uplink[j] * fu_all[t] + cc + downlink[j] * fd_all[t]
                answered = deadline is None or y <= deadline
                loc = local[j] * fr
                if decision.hedge:
                    after = decision.hedge_after_s
                    if answered:
                        lat = pre + min(y, after + loc)
                        ran_local = after + loc <= y  # else stopped (or never started)
                    else:
                        lat = pre + min(after, float(deadline or 0.0)) + loc
                        ran_local = True
                    cost = (
                        hedge_cost[j] if after <= 0.0 else self._delayed_hedge_cost(table, j, after)
                    )
                    hedged[t] = True
                elif answered:
                    lat = pre + y
                    cost = plain[j]
                    ran_local = False
                else:
                    pre = head[j] * fr  # a segment's tail never ran
                    lat = pre + float(deadline or 0.0) + loc
                    cost = plain[j]
                    ran_local = True
                outcome = Outcome(
                    prefix_s=pre,
                    cloud_s=y if answered else None,
                    cloud_compute_s=cc if answered else None,
                    bytes_up=sent,
                    local_s=loc if ran_local else None,
                    latency_s=lat,
                    waited_s=None if answered else deadline,
                    keyframe=is_key,
                )
                stream_whole = j in video and answered
            policy.observe(decision, outcome)
            column[t] = j
            latency[t] = lat
            served[t] = cost
        oracle_cost = np.array([self.segments[s].oracle_cost for s in range(len(self.segments))])
        return SimResult(
            policy=label or spec,
            frames_per_second=self.trace.frames_per_second,
            segment_starts=self.trace.segment_starts,
            segment_names=[s.name for s in self.trace.segments],
            actions=cuts.labels,
            column=column,
            hedged=hedged,
            latency_s=latency,
            served_cost=served,
            oracle_cost=oracle_cost[self.segment_of],
            oracle_latency_s=self._oracle_latency,
            decision_ns=decision_ns,
            extra={"state": policy.state()},
        )


def simulate(
    profile: Mapping[str, Any] | CutTable,
    trace: Trace,
    policy: str,
    *,
    seed: int = 0,
    params: Mapping[str, Any] | None = None,
    objective: Objective | Mapping[str, Any] | None = None,
    trace_dir: Path | None = None,
) -> SimResult:
    """Replay `trace` against `policy` with the costs of `profile` (one-call form)."""
    sim = Simulator(
        actions_table(profile), trace, seed=seed, objective=objective, trace_dir=trace_dir
    )
    return sim.run(policy, params)


def parse_policy_list(text: str) -> list[str]:
    """`elastic,ans,robot` → ["elastic", "ans", "robot"]; UserError when empty or repeated."""
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise UserError("--compare needs a comma-separated list of policies")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise UserError(f"--compare lists {', '.join(repeated)} more than once")
    return names


def markdown_table(results: Sequence[SimResult]) -> str:
    """A markdown table comparing runs on the same trace and seed."""
    n_segments = len(results[0].segment_starts) if results else 0
    head = [
        "policy",
        "mean latency (s)",
        "p95 (s)",
        "ratio to oracle",
        "regret",
        *[f"seg {i} settle" for i in range(n_segments)],
        "decision µs",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for res in results:
        s = res.summary()
        settles = ["never" if v is None else str(v) for v in res.settle_frames()]
        row = [
            res.policy,
            f"{s['mean_latency_s']:.3f}",
            f"{s['p95_latency_s']:.3f}",
            f"{s['ratio_to_oracle']:.3f}",
            f"{s['cumulative_regret']:.1f}",
            *settles,
            f"{s['decision_us_median']:.1f}",
        ]
        lines.append("| " + " | ".join(row) + " |")
    if results:
        oracle = results[0].oracle_latency_s.mean()
        lines.append(f"\noracle mean latency: {oracle:.3f} s")
    return "\n".join(lines)


def rolling_mean(values: FloatArray, window: int) -> FloatArray:
    """Trailing mean over `window` frames (shorter at the start)."""
    sums = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, values.size + 1)
    lo = np.maximum(idx - window, 0)
    return (sums[idx] - sums[lo]) / (idx - lo)


PLOT_SMOOTH_FRAMES = 20
# Policies whose mean latencies differ more than this share a log axis, or the best ones flatten.
LOG_SCALE_RATIO = 4.0


def plot_results(results: Sequence[SimResult], path: Path, title: str) -> None:
    """One PNG: latency over time (20-frame trailing mean) per policy, the oracle dashed,
    segment boundaries marked."""
    from common.extras import Extra, require

    matplotlib = require("matplotlib", Extra.PLOTS, "--plot")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not results:
        raise UserError("nothing to plot")
    first = results[0]
    t = np.arange(first.frames) / first.frames_per_second
    fig, ax = plt.subplots(figsize=(10, 4.5), dpi=110)
    try:
        for res in results:
            ax.plot(t, rolling_mean(res.latency_s, PLOT_SMOOTH_FRAMES), lw=1.2, label=res.policy)
        ax.plot(
            t,
            rolling_mean(first.oracle_latency_s, PLOT_SMOOTH_FRAMES),
            "k--",
            lw=1,
            label="oracle",
        )
        for start in first.segment_starts[1:]:
            ax.axvline(start / first.frames_per_second, color="grey", ls=":", lw=1)
        means = [float(r.latency_s.mean()) for r in results]
        if min(means) > 0 and max(means) / min(means) > LOG_SCALE_RATIO:
            ax.set_yscale("log")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"latency (s), {PLOT_SMOOTH_FRAMES}-frame mean")
        ax.set_title(title)
        ax.legend(loc="best", fontsize="small")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        try:
            fig.savefig(path)
        except OSError as exc:
            raise UserError(f"--plot {path}: cannot write ({exc.strerror or exc})") from None
    finally:
        plt.close(fig)
