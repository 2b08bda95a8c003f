"""zoo:stereo stage by stage: the tensor each stage hands on (bytes per frame) and the time each
stage takes on one core, at 320×240 and 640×480 (or the sizes given).

Each stage is its own onnxruntime session (one intra-op thread, default session options) fed
with the previous stage's real output on a textured pair; the whole model is timed too. Times
are the minimum over --runs runs (a shared host's load only ever adds time).

    python benchmarks/stereo_stages.py [--sizes 320x240,640x480] [--runs 5] [--json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from typing import Any

import numpy as np
import onnxruntime as ort

from nav.camera import CameraModel
from nav.stereo_graph import STAGE_ORDER, StereoPipeline, build_model
from nav.stereo_params import StereoParams, zoo_disparities

_ELEMENT_BYTES = {"tensor(uint8)": 1, "tensor(bool)": 1, "tensor(float)": 4}


def _session(model: Any) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    return ort.InferenceSession(
        model.SerializeToString(), options, providers=["CPUExecutionProvider"]
    )


def _best_ms(session: ort.InferenceSession, feeds: dict[str, np.ndarray], runs: int) -> float:
    session.run(None, feeds)  # warm-up
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        session.run(None, feeds)
        times.append(time.perf_counter() - start)
    return 1000.0 * min(times)


def _pair(height: int, width: int, disparity_px: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (1, height, width, 3), dtype=np.uint8)
    return {"left": left, "right": np.roll(left, -disparity_px, axis=2)}


def measure(width: int, height: int, runs: int) -> dict[str, Any]:
    d = zoo_disparities(width)
    pipeline = StereoPipeline(StereoParams(d), CameraModel.for_image(width, height))
    feeds = _pair(height, width, d // 4)
    full = _best_ms(_session(build_model(pipeline, height=height, width=width)), feeds, runs)
    rows = [{"stage": "left + right", "bytes": 2 * height * width * 3, "ms": 0.0}]
    for first, last in itertools.pairwise(STAGE_ORDER):
        session = _session(build_model(pipeline, first, last, height, width))
        ms = _best_ms(session, feeds, runs)
        (output,) = session.run(None, feeds)
        out_type = session.get_outputs()[0].type
        rows.append(
            {
                "stage": last.value,
                "bytes": int(output.size) * _ELEMENT_BYTES[out_type],
                "ms": round(ms, 1),
            }
        )
        feeds = {last.value: output}
    return {
        "size": f"{width}x{height}",
        "max_disparity": d,
        "full_ms": round(full, 1),
        "stages": rows,
    }


def markdown(results: list[dict[str, Any]]) -> str:
    head = "| tensor (made by the stage) |"
    rule = "|---|"
    for r in results:
        head += f" {r['size']} bytes | ms |"
        rule += "---:|---:|"
    lines = [head, rule]
    for i, row in enumerate(results[0]["stages"]):
        line = f"| {row['stage']} |"
        for r in results:
            cell = r["stages"][i]
            line += f" {_fmt_bytes(cell['bytes'])} | {cell['ms']:.1f} |"
        lines.append(line)
    line = "| whole model |"
    for r in results:
        line += f" (D = {r['max_disparity']}) | {r['full_ms']:.1f} |"
    lines.append(line)
    return "\n".join(lines)


def _fmt_bytes(n: int) -> str:
    if n >= 1 << 20:
        return f"{n / (1 << 20):.2f} MiB"
    if n >= 1 << 10:
        return f"{n / (1 << 10):.1f} KiB"
    return f"{n} B"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="320x240,640x480", help="WxH,WxH,...")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--json", action="store_true", help="Print JSON instead of markdown.")
    args = parser.parse_args()
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    results = [measure(w, h, args.runs) for w, h in sizes]
    if args.json:
        print(json.dumps({"results": results}, indent=2))
    else:
        print(markdown(results))


if __name__ == "__main__":
    main()
