"""Disparity accuracy on a real stereo pair with ground truth: zoo:stereo's matcher against
OpenCV's StereoBM and StereoSGBM over the same disparity range.

The pair is Middlebury 2014's Motorcycle as scikit-image ships it (741×500, nothing is
downloaded). bad-2 counts a pixel with known ground truth as wrong when its disparity is off by
more than 2 px or missing; density is the share that has one (nav.stereo_eval). OpenCV's matchers
run at a few block sizes (their other settings are OpenCV's defaults) so that ours is compared
with their best; ours is shown at a few windows and uniqueness ratios around the defaults (the
tuning; every variant has the 8-point census and the left-right check within 1 px). Times are
the fastest of three runs on one thread (onnxruntime intra-op threads = 1, cv2 threads = 1).

    python benchmarks/stereo_accuracy.py [--max-disparity 64] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import cv2
import numpy as np

from nav.disparity import DisparityRunner
from nav.stereo_eval import bad_pixels, opencv_disparity, stereo_motorcycle
from nav.stereo_params import (
    DEFAULT_MAX_COST_SHARE,
    DEFAULT_MIN_SUPPORT,
    DEFAULT_UNIQUENESS,
    DEFAULT_WINDOW_PX,
    StereoParams,
)

BM_BLOCKS = (5, 9, 15, 21)
SGBM_BLOCKS = (3, 5)
# Times are the fastest of these runs (a shared host's load only ever adds time).
TIMED_RUNS = 3
# (window, uniqueness, cost share, min support) variants of ours; the first is the default, the
# last two have no cost-share check and no small-region filter.
OURS = (
    (DEFAULT_WINDOW_PX, DEFAULT_UNIQUENESS, DEFAULT_MAX_COST_SHARE, DEFAULT_MIN_SUPPORT),
    (7, 0.05, 0.3, 8),
    (11, 0.05, 0.3, 8),
    (9, 0.0, 0.3, 8),
    (9, 0.10, 0.3, 8),
    (9, 0.05, 1.0, 8),
    (9, 0.05, 0.3, 0),
)


def measure(max_disparity: int) -> list[dict[str, Any]]:
    left, right, truth = stereo_motorcycle()
    rows = []

    def row(method: str, setting: str, disparity: np.ndarray, seconds: float) -> None:
        bad2 = bad_pixels(disparity, truth, 2.0)
        bad1 = bad_pixels(disparity, truth, 1.0)
        rows.append(
            {
                "method": method,
                "setting": setting,
                "bad2": round(bad2.bad, 4),
                "bad1": round(bad1.bad, 4),
                "density": round(bad2.density, 4),
                "seconds": round(seconds, 3),
            }
        )

    for window, uniqueness, share, support in OURS:
        params = StereoParams(
            max_disparity,
            window_px=window,
            uniqueness=uniqueness,
            max_cost_share=share,
            min_support=support,
        )
        runner = DisparityRunner(params, threads=1)
        runner(left, right)  # warm-up: the first run allocates
        results = [runner(left, right) for _ in range(TIMED_RUNS)]
        setting = (
            f"window {window}, uniqueness {uniqueness:g}, cost share {share:g}, "
            f"min support {support}"
        )
        row("ours (zoo:stereo)", setting, results[0].disparity, min(r.seconds for r in results))
    cv2.setNumThreads(1)
    for method, blocks in (("bm", BM_BLOCKS), ("sgbm", SGBM_BLOCKS)):
        for block in blocks:
            times = []
            for _ in range(TIMED_RUNS):
                start = time.perf_counter()
                disparity = opencv_disparity(left, right, max_disparity, method, block)
                times.append(time.perf_counter() - start)
            name = "OpenCV StereoBM" if method == "bm" else "OpenCV StereoSGBM"
            row(name, f"block {block}", disparity, min(times))
    return rows


def markdown(rows: list[dict[str, Any]], max_disparity: int) -> str:
    lines = [
        f"Motorcycle (Middlebury 2014, 741x500), disparities 0..{max_disparity - 1}; "
        "invalid counts as wrong",
        "",
        "| method | setting | bad-2 | bad-1 | density | time (1 thread) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['setting']} | {100 * r['bad2']:.1f}% | "
            f"{100 * r['bad1']:.1f}% | {100 * r['density']:.1f}% | {r['seconds']:.2f} s |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--max-disparity", type=int, default=64)
    parser.add_argument("--json", action="store_true", help="Print JSON instead of markdown.")
    args = parser.parse_args()
    rows = measure(args.max_disparity)
    if args.json:
        print(json.dumps({"max_disparity": args.max_disparity, "results": rows}, indent=2))
    else:
        print(markdown(rows, args.max_disparity))


if __name__ == "__main__":
    main()
