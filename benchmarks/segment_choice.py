"""Where `elastic` with segments chooses option 3, in the simulator, against options 1-4.

zoo:stereo's five cuts at 320×240 and 640×480 (bytes and stage times from docs/navigation.md,
"zoo:stereo: the stages"; every cut raw, as the stereo fleet's fidelity default admits no JPEG)
with every segment between two cuts (a split made with `cuts.segments`), under two conditions:

- `testbed`: the robot at half the profiling host, the cloud at its speed at every stage (the
  testbed's cloud runs on the same cores), 100 Mbit/s both ways, 2 ms RTT.
- `tail-slow cloud`: the cloud runs the stereo stages 10× faster than the profiling host but the
  d_coll stage (points → d_coll) at half its speed (an accelerator that runs the binning ops
  badly), the robot at the host's speed, 100 Mbit/s up, 1 Gbit/s down: the premise of the
  dominance pruning (a robot no faster than the cloud) fails at the tail.

Each condition is one stationary trace; every policy meets the same seeded jitter (σ 0.1). The
rows give each option's expected latency (the simulator's ground truth), and the mean latency of
`elastic` over whole suffixes (`segments: false`) and of `elastic` with the segments, with the
share of its frames on option 3 (the segment 0 → points) and on any segment.

    python benchmarks/segment_choice.py [--frames 5000] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any

import numpy as np

from robotd.policies.base import CutTable
from robotd.sim.simulator import Simulator
from robotd.sim.trace import trace_from_dict

POINTS = 4
D_COLL_BYTES = 164
# (cut bytes, stage ms that produces the cut's tensors), cuts 0..4, then the d_coll stage's ms.
STAGES: dict[str, tuple[list[tuple[int, float]], float]] = {
    "320x240": (
        [(460_800, 0.0), (153_600, 1.1), (1_228_800, 1.8), (307_200, 83.3), (921_600, 3.8)],
        7.9,
    ),
    "640x480": (
        [
            (1_843_200, 0.0),
            (614_400, 5.1),
            (4_915_200, 11.0),
            (1_228_800, 759.9),
            (3_686_400, 15.8),
        ],
        33.1,
    ),
}
"""Cut 3's stage is cost + cost_agg + disparity (the partitioner's cut list has no cut between)."""
CONDITIONS: dict[str, dict[str, float]] = {
    "testbed": {"robot_cpu": 0.5, "stereo_speedup": 1.0, "tail_speedup": 1.0, "down_mbit": 100.0},
    "tail-slow cloud": {
        "robot_cpu": 1.0, "stereo_speedup": 10.0, "tail_speedup": 0.5, "down_mbit": 1000.0,
    },
}  # fmt: skip
UPLINK_MBIT = 100.0
RTT_MS = 2.0
JITTER = 0.1


def stereo_profile(size: str) -> dict[str, Any]:
    """The profile of zoo:stereo at `size`, with every segment between two cuts."""
    rows, tail_ms = STAGES[size]
    full_ms = sum(ms for _, ms in rows) + tail_ms
    cuts, done = [], 0.0
    for k, (size_bytes, ms) in enumerate(rows):
        done += ms
        cuts.append(
            {"index": k, "bytes": size_bytes, "prefix_ms": done, "suffix_ms": full_ms - done}
        )
    pairs = [[a, b] for a in range(len(rows)) for b in range(a + 1, len(rows))]
    return {"full_ms": full_ms, "output_bytes": D_COLL_BYTES, "cuts": cuts, "segments": pairs}


def condition_table(size: str, condition: dict[str, float]) -> CutTable:
    """The actions as this condition's cloud runs them: each whole suffix's cloud time is its
    stereo part at `stereo_speedup` and the d_coll stage at `tail_speedup` (the trace's
    cloud_speedup is then 1); a segment ending at the points leaves the tail to the robot."""
    profile = stereo_profile(size)
    table = CutTable.from_profile(profile)
    tail_s = STAGES[size][1] / 1000
    stereo_s = np.maximum(table.cloud_s - tail_s, 0.0)
    cloud = stereo_s / condition["stereo_speedup"] + tail_s / condition["tail_speedup"]
    return dataclasses.replace(table, cloud_s=cloud).with_segments(profile["segments"])


def run_condition(size: str, name: str, frames: int, seed: int) -> dict[str, Any]:
    condition = CONDITIONS[name]
    table = condition_table(size, condition)
    trace = trace_from_dict(
        {
            "frames_per_second": 10,
            "noise": {"jitter": JITTER},
            "segments": [
                {
                    "frames": frames,
                    "uplink_mbit": UPLINK_MBIT,
                    "downlink_mbit": condition["down_mbit"],
                    "rtt_ms": RTT_MS,
                    "robot_cpu": condition["robot_cpu"],
                    "cloud_speedup": 1.0,
                }
            ],
        }
    )
    sim = Simulator(table, trace, seed=seed)
    truth = sim.segments[0].latency_plain
    options = {
        "1": truth[table.position(0)],
        "2": truth[table.position(POINTS)],
        "3": truth[table.position(0, end=POINTS)],
        "4": truth[table.size],
    }
    row: dict[str, Any] = {
        "size": size,
        "condition": name,
        "options_s": {k: round(float(v), 4) for k, v in options.items()},
        "best_action": table.labels[sim.segments[0].oracle],
        "oracle_s": round(float(truth[sim.segments[0].oracle]), 4),
    }
    whole_columns = [j for j in range(table.size + 1) if j == table.size or table.ends[j] is None]
    best_whole = min(whole_columns, key=lambda j: truth[j])
    row["best_whole"] = table.labels[best_whole]
    row["best_whole_s"] = round(float(truth[best_whole]), 4)
    whole = table.subset(whole_columns[:-1])
    # elastic as `segments: false` builds it (the whole suffixes), and with the segments.
    for key, cuts in (("elastic", whole), ("elastic_segments", table)):
        result = Simulator(cuts, trace, seed=seed).run("elastic")
        labels = cuts.labels
        served = [labels[c] for c in result.column.tolist()]
        second = served[frames // 2 :]
        row[key] = {
            "mean_s": round(float(result.latency_s.mean()), 4),
            "second_half_mean_s": round(float(result.latency_s[frames // 2 :].mean()), 4),
            "option3_share": round(served.count("0-4") / frames, 3),
            "segment_share": round(sum("-" in a for a in served) / frames, 3),
            "main_action": max(set(second), key=second.count),
        }
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000, help="frames per run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args(argv)
    if args.frames < 100:
        parser.error("--frames must be >= 100")
    rows = [
        run_condition(size, name, args.frames, args.seed) for size in STAGES for name in CONDITIONS
    ]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print(
        "| size | condition | option 1 | option 2 | option 3 | option 4 | best action "
        "| best whole suffix | elastic (whole suffixes) | elastic with segments "
        "| its frames on option 3 | on any segment | its main action (2nd half) |"
    )
    print("|---|---|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---|")
    for r in rows:
        o, e, s = r["options_s"], r["elastic"], r["elastic_segments"]
        print(
            f"| {r['size']} | {r['condition']} | {o['1']:.3f} | {o['2']:.3f} | {o['3']:.3f} "
            f"| {o['4']:.3f} | {r['best_action']} ({r['oracle_s']:.3f}) "
            f"| {r['best_whole']} ({r['best_whole_s']:.3f}) | {e['mean_s']:.3f} "
            f"| {s['mean_s']:.3f} | {s['option3_share']:.0%} | {s['segment_share']:.0%} "
            f"| {s['main_action']} |"
        )


if __name__ == "__main__":
    main()
