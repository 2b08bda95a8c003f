"""Split + verify time and cut counts for the zoo models (the figures in docs/partitioning.md).

Each model is exported into a fresh cache directory, then split and verified into a temporary
directory, timed separately. With ``--profile-runs N`` the cuts are also profiled (median of N).
Prints a markdown table; ``--json`` prints the raw figures instead.

    python benchmarks/partition_bench.py [--shape 3x240x320] [--models vgg,resnet,mobilenet]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def bench_model(name: str, shape: tuple[int, ...], profile_runs: int) -> dict[str, Any]:
    from common.models import resolve_model
    from common.partition import DOMINATED_PREFIX, split_model

    t0 = time.perf_counter()
    ref = resolve_model(f"zoo:{name}", shape)
    export_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        part = split_model(ref.path, Path(out))
        split_s = time.perf_counter() - t0
        weights = (Path(out) / "weights.bin").stat().st_size
    dominated = sum(e.reason.startswith(DOMINATED_PREFIX) for e in part.excluded)
    total = part.cuts[0].suffix_flops

    def min_bytes(share: float) -> int:
        return min(c.bytes for c in part.cuts if c.prefix_flops <= share * total)

    row: dict[str, Any] = {
        "model": name,
        "export_s": round(export_s, 2),
        "split_verify_s": round(split_s, 2),
        "cuts": len(part.cuts),
        "two_tensor_cuts": sum(len(c.tensors) == 2 for c in part.cuts),
        "dominated": dominated,
        "failed": len(part.excluded) - dominated,
        "max_abs_err": max(c.max_abs_err or 0.0 for c in part.cuts),
        "gflops": round(total / 1e9, 3),
        "weights_mb": round(weights / 1e6, 2),
        "input_kb": part.cuts[0].bytes / 1024,
        "min_kb_25": min_bytes(0.25) / 1024,
        "min_kb_50": min_bytes(0.50) / 1024,
        "min_kb_75": min_bytes(0.75) / 1024,
    }
    if profile_runs:
        from common.partition import load_partition, sample_feeds
        from common.partition.runtime import SplitModel
        from common.profiler import median_ms, profile_model

        t0 = time.perf_counter()
        prof = profile_model(str(ref.path), runs=profile_runs, refresh=True)
        row["profile_s"] = round(time.perf_counter() - t0, 2)
        row["full_ms"] = prof["full_ms"]
        # The same full model with onnxruntime's NCHWc layout (optimization="all"), which would
        # give every session its own copy of the convolution weights.
        fast = SplitModel(load_partition(str(ref.path)), optimization="all", lazy=True)
        feeds = sample_feeds(fast.input_specs())
        row["full_ms_all"] = round(median_ms(lambda: fast.run_full(feeds), profile_runs), 2)
    return row


def markdown(rows: list[dict[str, Any]], shape: tuple[int, ...]) -> str:
    cols = [
        ("model", "model"),
        ("export_s", "export s"),
        ("split_verify_s", "split+verify s"),
        ("cuts", "cuts"),
        ("two_tensor_cuts", "2-tensor cuts"),
        ("dominated", "dominated (left out)"),
        ("failed", "failed"),
        ("max_abs_err", "max abs err"),
        ("gflops", "GFLOP"),
        ("weights_mb", "weights MB"),
        ("min_kb_25", "KiB sent, ≤25% FLOPs on robot"),
        ("min_kb_50", "≤50%"),
        ("min_kb_75", "≤75%"),
    ]
    if rows and "full_ms" in rows[0]:
        cols += [
            ("profile_s", "profile s"),
            ("full_ms", "full ms (shared weights)"),
            ("full_ms_all", "full ms (NCHWc, unshared)"),
        ]
    lines = [
        f"input 1x{'x'.join(map(str, shape))} (cut 0 sends {rows[0]['input_kb']:.0f} KiB)",
        "",
        "| " + " | ".join(title for _, title in cols) + " |",
        "|" + "|".join("---" for _ in cols) + "|",
    ]
    for row in rows:
        cells = []
        for key, _ in cols:
            value = row[key]
            if key.startswith("min_kb"):
                cells.append(f"{value:.0f}")
            elif key == "max_abs_err":
                cells.append(f"{value:.1g}")
            elif isinstance(value, float):
                cells.append(f"{value:.2f}")
            else:
                cells.append(str(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shape", default="3x240x320", help="zoo input shape CxHxW")
    parser.add_argument("--models", default="vgg,resnet,mobilenet")
    parser.add_argument("--profile-runs", type=int, default=0, help="also profile (0: skip)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    shape = tuple(int(d) for d in args.shape.split("x"))
    with tempfile.TemporaryDirectory() as cache:
        # A fresh cache: every model is exported and split here, nothing is reused.
        os.environ["ELASTICFOG_CACHE_DIR"] = cache
        rows = [bench_model(m, shape, args.profile_runs) for m in args.models.split(",")]
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"host: {platform.machine()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}")
        print(markdown(rows, shape))
    return 0


if __name__ == "__main__":
    sys.exit(main())
