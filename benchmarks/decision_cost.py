"""Decision cost of ElasticAction per frame: Sherman–Morrison against inverting Q every frame.

Both implementations run side by side in one process on the same synthetic profile (16 cuts by
default, each with 4 codecs: 64 offloading actions and P, context d = 3) and the same stream of
frames and outcomes, and must make the same decisions. For each, `decide` (what delays a frame),
`observe` (the learning after it) and their sum per frame (the policy's whole per-frame work) are
timed; the table gives medians in µs.

- "Sherman–Morrison": the shipped `elastic` policy (Q⁻¹ kept current at each update).
- "inverts Q every frame": the same policy whose `observe` only accumulates Q and p, and whose
  `decide` inverts Q (numpy) and recomputes α̂, the predictions and widths before choosing.

    python benchmarks/decision_cost.py [--frames 20000] [--cuts 16] [--codecs 4] [--uplink-mbit 10]
                                       [--seed 0] [--segments]

Every (cut, codec) stays an action (`prune_dominated` off): the worst case for the decision.
`--segments` adds the segment between every two cuts, once per codec of its start cut (a split
made with `cuts.segments`), and with it the fourth context feature, MB returned (d = 4): with
`--cuts 5 --codecs 4` that is zoo:stereo's largest action set, 20 whole suffixes and 40 segments.
"""

from __future__ import annotations

import argparse
import gc
import statistics
import time
from typing import Any

import numpy as np

from robotd.policies import FrameContext, Outcome, make_policy
from robotd.policies.base import PURE_ROBOT, Decision, FloatArray
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.ridge import RidgeEstimator

WARMUP_FRAMES = 1000
ROBOT_SLOWDOWN = 20.0  # robot time / profiled time
RTT_S = 0.01
CLOUD_SPEEDUP = 8.0
JITTER = 0.05
BITS_PER_BYTE = 8
MBIT = 1e6


# (codec, share of the raw bytes, encode ms, decode ms): the first N are each cut's codecs.
CODECS = (
    ("raw", 1.0, 0.0, 0.0),
    ("raw+zstd", 0.7, 0.4, 0.2),
    ("fp16", 0.5, 0.2, 0.1),
    ("int8", 0.25, 0.3, 0.1),
    ("int8+zstd", 0.15, 0.5, 0.2),
)


def synthetic_profile(cuts: int, codecs: int = 4, segments: bool = False) -> dict[str, Any]:
    """A chain CNN-like profile: time grows along the net, bytes shrink (cut 0 = raw input);
    every cut crosses in each of the first `codecs` of CODECS; with `segments`, the segment
    between every two cuts is listed (as `robotd.robot_profile` lists a split's)."""
    full_ms = 72.9
    rows = []
    for k in range(cuts):
        share = k / cuts
        raw = int(921_600 * 0.72**k) + 4096
        rows.append(
            {
                "index": k,
                "bytes": raw,
                "prefix_ms": round(full_ms * share, 3),
                "suffix_ms": round(full_ms * (1 - share), 3),
                "codecs": [
                    {"name": name, "bytes": raw * ratio, "encode_ms": enc, "decode_ms": dec}
                    for name, ratio, enc, dec in CODECS[:codecs]
                ],
            }
        )
    pairs = [[a, b] for a in range(cuts) for b in range(a + 1, cuts)] if segments else []
    return {"full_ms": full_ms, "cuts": rows, **({"segments": pairs} if pairs else {})}


class InvertingRidge(RidgeEstimator):
    """Accumulates Q and p only; `solve` inverts Q and recomputes α̂ (the baseline compared)."""

    q: FloatArray
    p_vec: FloatArray

    def reset(self) -> None:
        super().reset()
        self.q = np.eye(self.d) * self.gamma
        self.p_vec = np.zeros(self.d)

    def _add(self, v: list[float], y: float) -> None:
        self.samples += 1
        vec = np.array(v)
        self.q += np.outer(vec, vec)
        self.p_vec += vec * y

    def solve(self) -> None:
        q_inv = np.linalg.inv(self.q)
        self._q = q_inv.ravel().tolist()
        self.alpha = (q_inv @ self.p_vec).tolist()


class InvertEveryFrame(ElasticPolicy):
    """ElasticAction that inverts Q and recomputes every score at each decision."""

    ridge_type = InvertingRidge
    _ridge: InvertingRidge

    def _refresh(self, learned: bool) -> None:
        """Nothing to keep current between frames: `decide` recomputes everything."""

    def decide(self, ctx: FrameContext) -> Decision:
        self._ridge.solve()
        super()._refresh(learned=True)
        return super().decide(ctx)


def outcome_for(
    profile: dict[str, Any], decision: Decision, rng: np.random.Generator, uplink_mbit: float
) -> Outcome:
    """What a robot would measure for this decision under fixed conditions with jitter.

    Python floats, as the robot's clocks give them (numpy scalars would slow the arithmetic).
    """
    noise = rng.lognormal(-(JITTER**2) / 2, JITTER, size=3).tolist()
    if decision.action == PURE_ROBOT:
        full = profile["full_ms"] / 1000 * ROBOT_SLOWDOWN * noise[0]
        return Outcome(prefix_s=full, latency_s=full)
    cut = profile["cuts"][int(decision.action)]
    sent = int(next(c["bytes"] for c in cut["codecs"] if c["name"] == decision.codec))
    # A segment: the robot also runs the tail after the reply, which brings the end cut back.
    end = None if decision.end is None else profile["cuts"][decision.end]
    tail_ms = 0.0 if end is None else end["suffix_ms"]
    back = 0 if end is None else end["bytes"]
    prefix = (cut["prefix_ms"] + tail_ms) / 1000 * ROBOT_SLOWDOWN * noise[0]
    compute = (cut["suffix_ms"] - tail_ms) / 1000 / CLOUD_SPEEDUP * noise[1]
    transfer_s = (sent + back) * BITS_PER_BYTE / (uplink_mbit * MBIT)
    y = (transfer_s + RTT_S) * noise[2] + compute
    local = cut["suffix_ms"] / 1000 * ROBOT_SLOWDOWN * noise[0] if decision.hedge else None
    return Outcome(
        prefix_s=prefix,
        cloud_s=y,
        cloud_compute_s=compute,
        bytes_up=sent,
        local_s=local,
        latency_s=prefix + (y if local is None else min(y, local)),
    )


def _key(d: Decision) -> tuple[Any, ...]:
    return (d.action, d.codec, d.end, d.hedge, d.forced, d.updating)


def run(
    frames: int,
    cuts: int,
    seed: int,
    uplink_mbit: float = 10.0,
    codecs: int = 4,
    segments: bool = False,
) -> dict[str, Any]:
    """Time both implementations on the same frames; µs medians per implementation."""
    profile = synthetic_profile(cuts, codecs, segments)
    fast = make_policy("elastic", profile, {"prune_dominated": False})
    assert isinstance(fast, ElasticPolicy)
    slow = InvertEveryFrame(fast.cuts, fast.params, fast.objective, "elastic-invert")
    policies = {"fast": fast, "slow": slow}
    rng = np.random.default_rng(seed)
    entropies = rng.uniform(0.5, 1.0, size=frames + WARMUP_FRAMES)
    decide_ns: dict[str, list[int]] = {"fast": [], "slow": []}
    observe_ns: dict[str, list[int]] = {"fast": [], "slow": []}
    mismatches = offloaded = hedged = on_segments = 0
    clock = time.perf_counter_ns
    gc.disable()
    try:
        for t in range(frames + WARMUP_FRAMES):
            ctx = FrameContext(index=t, entropy=float(entropies[t]))
            decisions = {}
            # Alternate which one goes first, so neither always runs with warmer caches.
            for key in ("fast", "slow") if t % 2 == 0 else ("slow", "fast"):
                policy = policies[key]
                started = clock()
                decision = policy.decide(ctx)
                decided = clock()
                outcome = outcome_for(
                    profile, decision, np.random.default_rng((seed, t)), uplink_mbit
                )
                observing = clock()
                policy.observe(decision, outcome)
                done = clock()
                decisions[key] = decision
                if t >= WARMUP_FRAMES:
                    decide_ns[key].append(decided - started)
                    observe_ns[key].append(done - observing)
            mismatches += _key(decisions["fast"]) != _key(decisions["slow"])
            if t >= WARMUP_FRAMES:
                offloaded += decisions["fast"].offloads
                hedged += decisions["fast"].hedge
                on_segments += decisions["fast"].end is not None
    finally:
        gc.enable()
    report: dict[str, Any] = {
        "mismatched_decisions": mismatches,
        "actions": fast.cuts.size + 1,
        "features": fast.contexts.shape[1],
    }
    for key in policies:
        frame_ns = [a + b for a, b in zip(decide_ns[key], observe_ns[key], strict=True)]
        report[key] = {
            "decide_median_us": statistics.median(decide_ns[key]) / 1000,
            "observe_median_us": statistics.median(observe_ns[key]) / 1000,
            "frame_median_us": statistics.median(frame_ns) / 1000,
            "frame_p90_us": float(np.percentile(frame_ns, 90)) / 1000,
        }
    report["offloaded_share"] = offloaded / frames
    report["hedged_share"] = hedged / frames
    report["segment_share"] = on_segments / frames
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="timed frames")
    parser.add_argument("--cuts", type=int, default=16, help="number of cuts")
    parser.add_argument(
        "--codecs", type=int, default=4, help=f"codecs per cut (1 to {len(CODECS)})"
    )
    parser.add_argument(
        "--uplink-mbit", type=float, default=10.0, help="uplink of the simulated link, Mbit/s"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--segments",
        action="store_true",
        help="also the segment between every two cuts, per codec of its start cut",
    )
    args = parser.parse_args()
    if args.frames < 1 or args.cuts < 1 or args.uplink_mbit <= 0:
        parser.error("--frames and --cuts must be >= 1 and --uplink-mbit > 0")
    if not 1 <= args.codecs <= len(CODECS):
        parser.error(f"--codecs must be 1 to {len(CODECS)}")
    report = run(args.frames, args.cuts, args.seed, args.uplink_mbit, args.codecs, args.segments)
    shape = f"{args.cuts} cuts x {args.codecs} codecs" + (" with segments" if args.segments else "")
    print(
        f"ElasticAction decision cost: {shape}, {report['actions']} actions with P, "
        f"d={report['features']}, {args.frames} frames "
        f"({report['offloaded_share']:.0%} offloaded, {report['hedged_share']:.0%} hedged, "
        f"{report['segment_share']:.0%} on segments), {args.uplink_mbit:g} Mbit/s, "
        f"seed {args.seed}\n"
    )
    print(
        "| implementation | decide median (µs) | observe median (µs) "
        "| decide+observe median (µs) | decide+observe p90 (µs) |"
    )
    print("|---|---|---|---|---|")
    names = {"fast": "Sherman–Morrison (shipped)", "slow": "inverts Q every frame"}
    for key in ("fast", "slow"):
        r = report[key]
        print(
            f"| {names[key]} | {r['decide_median_us']:.1f} | {r['observe_median_us']:.1f} "
            f"| {r['frame_median_us']:.1f} | {r['frame_p90_us']:.1f} |"
        )
    print(f"\ndecisions that differ between the two: {report['mismatched_decisions']}")


if __name__ == "__main__":
    main()
