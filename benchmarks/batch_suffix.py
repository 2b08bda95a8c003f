"""What one more request in a batch costs: a batched suffix's CPU time per frame at batch sizes.

The cloud daemon's dynamic batching pays only where a bigger batch costs less per frame. This
runs a model's suffix the way a deployment serves it (`SplitModel`, shared weights, the cloud's
session options, `enable_batching`) on batches of 1, 2, 4 and 8 frames of photographs, and
reports per frame the process CPU time (`time.process_time`, what "frames per core" divides by)
and the wall time, median of the rounds. Sizes run interleaved round by round, so a neighbour's
load on a shared host falls on all of them alike. The last column is CPU per frame at batch 1
over CPU per frame at each size: the most batching can gain on this host for this suffix.

    python benchmarks/batch_suffix.py [--model zoo:resnet] [--input-shape 3x240x320]
        [--cuts 0,mid,last] [--threads 1] [--rounds 9] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from typing import Any

from common.image_input import InputAdapter
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.photos import still_views
from common.zoo import parse_shape
from experiments.report import md_table

SIZES = (1, 2, 4, 8)
DEFAULT_ROUNDS = 9


def cut_indices(text: str, num_cuts: int) -> list[int]:
    """'0,mid,last' -> cut indices of this model."""
    named = {"mid": num_cuts // 2, "last": num_cuts - 1}
    return [named[p] if p in named else int(p) for p in text.split(",")]


def measure(model: SplitModel, cut: int, rounds: int) -> list[dict[str, Any]]:
    spec = model.input_specs()[0]
    adapter = InputAdapter(spec)
    frames = [model.run_prefix(cut, {spec.name: adapter(v)}) for v in still_views(max(SIZES))]
    reason = model.enable_batching(cut)
    if reason is not None:
        raise SystemExit(f"cut {cut} cannot take a batch: {reason}")
    cpu: dict[int, list[float]] = {n: [] for n in SIZES}
    wall: dict[int, list[float]] = {n: [] for n in SIZES}
    for n in SIZES:  # warm each size once
        model.run_suffix_batch(cut, frames[:n])
    for _ in range(rounds):
        for n in SIZES:
            c0, w0 = time.process_time(), time.perf_counter()
            model.run_suffix_batch(cut, frames[:n])
            cpu[n].append((time.process_time() - c0) / n)
            wall[n].append((time.perf_counter() - w0) / n)
    base = statistics.median(cpu[1])
    return [
        {
            "cut": cut,
            "batch": n,
            "cpu_per_frame_ms": 1000 * statistics.median(cpu[n]),
            "wall_per_frame_ms": 1000 * statistics.median(wall[n]),
            "gain": base / statistics.median(cpu[n]),
        }
        for n in SIZES
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="zoo:resnet")
    parser.add_argument("--input-shape", default="3x240x320")
    parser.add_argument("--cuts", default="0,mid,last")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=DEFAULT_ROUNDS)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    partition = load_partition(args.model, input_shape=parse_shape(args.input_shape))
    model = SplitModel(partition, threads=args.threads or None, lazy=True)
    rows = []
    for cut in cut_indices(args.cuts, model.num_cuts):
        rows += measure(model, cut, args.rounds)
    if args.json:
        print(json.dumps({"model": args.model, "input_shape": args.input_shape, "rows": rows}))
        return
    print(f"{args.model} at {args.input_shape}, {args.threads} thread(s), {args.rounds} rounds\n")
    print(
        md_table(
            ["cut", "batch", "CPU ms/frame", "wall ms/frame", "CPU gain vs batch 1"],
            [
                [
                    r["cut"],
                    r["batch"],
                    f"{r['cpu_per_frame_ms']:.2f}",
                    f"{r['wall_per_frame_ms']:.2f}",
                    f"{r['gain']:.2f}x",
                ]
                for r in rows
            ],
        )
    )


if __name__ == "__main__":
    main()
