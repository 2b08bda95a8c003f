"""Decision cost of ElasticAction per frame: Sherman–Morrison against inverting Q every frame.

Both implementations run side by side in one process on the same synthetic 16-cut profile and the
same stream of frames and outcomes, and must make the same decisions. `decide` is timed alone
(what delays a frame) and together with `observe` (the policy's whole per-frame work).

    python benchmarks/decision_cost.py [--frames 20000] [--cuts 16] [--seed 0]
"""

from __future__ import annotations

import argparse
import gc
import statistics
import time
from typing import Any

import numpy as np

from robotd.policies import FrameContext, Outcome, make_policy
from robotd.policies.base import PURE_ROBOT, Decision
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.ridge import RidgeEstimator

WARMUP_FRAMES = 1000
ROBOT_SLOWDOWN = 20.0  # robot time / profiled time
UPLINK_BYTES_PER_S = 10e6 / 8
RTT_S = 0.01
CLOUD_SPEEDUP = 8.0
JITTER = 0.05


def synthetic_profile(cuts: int) -> dict[str, Any]:
    """A chain CNN-like profile: time grows along the net, bytes shrink (cut 0 = raw input)."""
    full_ms = 72.9
    rows = []
    for k in range(cuts):
        share = k / cuts
        rows.append(
            {
                "index": k,
                "bytes": int(921_600 * 0.72**k) + 4096,
                "prefix_ms": round(full_ms * share, 3),
                "suffix_ms": round(full_ms * (1 - share), 3),
            }
        )
    return {"full_ms": full_ms, "cuts": rows}


class _AccumulateOnly(RidgeEstimator):
    """Keeps Q and p only; the inverse is left to the per-frame inversion."""

    q: np.ndarray

    def reset(self) -> None:
        self.q = np.eye(self.d) * self.gamma
        super().reset()

    def update_vector(self, v: np.ndarray, y: float) -> None:
        self.q += np.outer(v, v)
        self.p += v * y
        self.samples += 1


class InvertEveryFrame(ElasticPolicy):
    """ElasticAction that inverts Q and recomputes α̂ and the widths at every decision."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._accumulator = _AccumulateOnly(self.contexts, self.params.gamma)
        self._ridge = self._accumulator
        self._refresh()

    def decide(self, ctx: FrameContext) -> Decision:
        ridge = self._accumulator
        ridge.q_inv = np.linalg.inv(ridge.q)
        ridge.refresh()
        self._refresh()
        return super().decide(ctx)


def outcome_for(profile: dict[str, Any], decision: Decision, rng: np.random.Generator) -> Outcome:
    """What a robot would measure for this decision under fixed conditions with jitter."""
    noise = rng.lognormal(-(JITTER**2) / 2, JITTER, size=3)
    if decision.action == PURE_ROBOT:
        full = profile["full_ms"] / 1000 * ROBOT_SLOWDOWN * noise[0]
        return Outcome(prefix_s=full, latency_s=full)
    cut = profile["cuts"][int(decision.action)]
    prefix = cut["prefix_ms"] / 1000 * ROBOT_SLOWDOWN * noise[0]
    compute = cut["suffix_ms"] / 1000 / CLOUD_SPEEDUP * noise[1]
    y = (cut["bytes"] / UPLINK_BYTES_PER_S + RTT_S) * noise[2] + compute
    local = cut["suffix_ms"] / 1000 * ROBOT_SLOWDOWN * noise[0] if decision.hedge else None
    return Outcome(
        prefix_s=prefix,
        cloud_s=y,
        cloud_compute_s=compute,
        bytes_up=cut["bytes"],
        local_s=local,
        latency_s=prefix + (y if local is None else min(y, local)),
    )


def run(frames: int, cuts: int, seed: int) -> dict[str, dict[str, float]]:
    """Time both implementations on the same frames; returns µs statistics per implementation."""
    profile = synthetic_profile(cuts)
    fast = make_policy("elastic", profile)
    assert isinstance(fast, ElasticPolicy)
    slow = InvertEveryFrame(fast.cuts, fast.params, fast.objective, "elastic-invert")
    rng = np.random.default_rng(seed)
    entropies = rng.uniform(0.5, 1.0, size=frames + WARMUP_FRAMES)
    timings: dict[str, tuple[list[int], list[int]]] = {"fast": ([], []), "slow": ([], [])}
    mismatches = 0
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for t in range(frames + WARMUP_FRAMES):
            ctx = FrameContext(index=t, entropy=float(entropies[t]))
            decisions = {}
            for key, policy in (("fast", fast), ("slow", slow)):
                started = clock()
                decisions[key] = policy.decide(ctx)
                decided = clock()
                outcome = outcome_for(profile, decisions[key], np.random.default_rng((seed, t)))
                observing = clock()
                policy.observe(decisions[key], outcome)
                done = clock()
                if t >= WARMUP_FRAMES:
                    timings[key][0].append(decided - started)
                    timings[key][1].append(decided - started + done - observing)
            mismatches += decisions["fast"].action != decisions["slow"].action
    finally:
        gc.enable()
    report = {}
    for key, (decide_ns, frame_ns) in timings.items():
        report[key] = {
            "decide_median_us": statistics.median(decide_ns) / 1000,
            "decide_p90_us": float(np.percentile(decide_ns, 90)) / 1000,
            "frame_median_us": statistics.median(frame_ns) / 1000,
        }
    report["fast"]["mismatched_decisions"] = mismatches
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="timed frames")
    parser.add_argument("--cuts", type=int, default=16, help="number of cuts (actions besides P)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.frames < 1 or args.cuts < 1:
        parser.error("--frames and --cuts must be >= 1")
    report = run(args.frames, args.cuts, args.seed)
    print(f"ElasticAction decision cost: {args.cuts} cuts, d=3, {args.frames} frames\n")
    print("| implementation | decide median (µs) | decide p90 (µs) | decide+observe median (µs) |")
    print("|---|---|---|---|")
    names = {"fast": "Sherman–Morrison, cached", "slow": "inverts Q every frame"}
    for key in ("fast", "slow"):
        r = report[key]
        print(
            f"| {names[key]} | {r['decide_median_us']:.1f} | {r['decide_p90_us']:.1f} "
            f"| {r['frame_median_us']:.1f} |"
        )
    print(f"\ndecisions that differ between the two: {int(report['fast']['mismatched_decisions'])}")


if __name__ == "__main__":
    main()
