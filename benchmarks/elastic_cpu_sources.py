"""Where `elastic`'s robot CPU per frame beyond a static policy of the same action comes from.

Against `cloud:jpeg50` (every frame cut 0 as JPEG 50), an `elastic` robot that also settles on
`cut:0:jpeg50` spends robot CPU on:

- its decision: `decide` + `observe` per frame (a static policy's are a table lookup);
- local runs of the whole model: an exploring frame (forced, or won by its confidence bonus),
  every offloaded frame of an update period and a robot probe are hedged, and the hedged local
  run (deferred while the reply is expected first, stopped when the reply comes) can run the
  whole model on the robot;
- other codecs' encodes: a forced sample of another (cut, codec) encodes the frame again.

Each part is timed alone here as process CPU time (one onnxruntime thread, so wall time on an
idle core), median and p95 of `--runs`, for zoo:mobilenet_v2 at each `--size`; how often each
happens per 100 frames comes from the simulator replaying `elastic` on a trace where cut 0 wins
throughout (a robot at 1/10 of this host on 12 Mbit/s, the §5 setting: `--robot-cpu`,
`--uplink-mbit`), with the model's own profile at that size. A hedged frame counts as a whole
local run (an upper bound: a deferred run that loses to the reply is stopped early).

    python benchmarks/elastic_cpu_sources.py [--size 224x224] [--size 640x480] [--runs 30] [--json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import onnxruntime as ort

from common.photos import still_views
from common.wire.tensor_codecs import encode_tensor_as
from common.zoo import export
from robotd.policies import FrameContext, Outcome, make_policy
from robotd.policies.base import CutTable
from robotd.sim import Simulator
from robotd.trace import trace_from_dict

MODEL = "mobilenet_v2"
FRAMES = 3000
MS = 1000.0
US = 1e6


def _cpu_times(fn: Any, runs: int) -> np.ndarray:
    out = []
    for _ in range(runs):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return np.asarray(out)


def _stats(seconds: np.ndarray, scale: float) -> dict[str, float]:
    return {
        "median": round(float(np.median(seconds)) * scale, 3),
        "p95": round(float(np.percentile(seconds, 95)) * scale, 3),
    }


def _profile(full_s: float, jpeg: dict[str, tuple[float, float]], raw_bytes: int) -> dict:
    """A two-action profile: cut 0 (raw and the JPEGs measured) and the whole model as P."""
    codecs = [{"name": "raw", "bytes": raw_bytes}]
    codecs += [
        {"name": name, "bytes": nbytes, "encode_ms": enc_s * MS}
        for name, (nbytes, enc_s) in jpeg.items()
    ]
    return {
        "full_ms": full_s * MS,
        "output_bytes": 4000,
        "cuts": [
            {
                "index": 0,
                "bytes": raw_bytes,
                "prefix_ms": 0.0,
                "suffix_ms": full_s * MS,
                "codecs": codecs,
            }
        ],
    }


def measure(width: int, height: int, runs: int, robot_cpu: float, uplink_mbit: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        path = export(MODEL, Path(tmp) / "m.onnx", (3, height, width))
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        session = ort.InferenceSession(str(path), options)
    frame = cv2.resize(still_views(1)[0], (width, height))[None]
    name = session.get_inputs()[0].name
    session.run(None, {name: frame})  # warm
    full = _cpu_times(lambda: session.run(None, {name: frame}), runs)
    jpeg: dict[str, tuple[float, float]] = {}
    encodes = {}
    for codec in ("jpeg50", "jpeg80"):
        enc = _cpu_times(lambda codec=codec: encode_tensor_as(frame, codec), runs)
        encodes[codec] = enc
        jpeg[codec] = (encode_tensor_as(frame, codec).nbytes, float(np.median(enc)))
    profile = _profile(float(np.median(full)), jpeg, int(frame.nbytes))
    # The decision itself, on this table: decide + observe of an offloaded frame.
    policy = make_policy("elastic", profile)
    static = make_policy("cloud:jpeg50", profile)

    def step(p: Any, t: list[int]) -> None:
        d = p.decide(FrameContext(t[0], 0.5))
        p.observe(d, Outcome(prefix_s=0.0, cloud_s=0.02, bytes_up=jpeg["jpeg50"][0]))
        t[0] += 1

    decision = _cpu_times(lambda t=[0]: step(policy, t), runs * 100)
    static_decision = _cpu_times(lambda t=[0]: step(static, t), runs * 100)
    trace = trace_from_dict(
        {
            "frames_per_second": 10,
            "noise": {"jitter": 0.05},
            "segments": [
                {
                    "frames": FRAMES,
                    "uplink_mbit": uplink_mbit,
                    "downlink_mbit": 100,
                    "rtt_ms": 5,
                    "robot_cpu": robot_cpu,
                    "cloud_speedup": 4,
                }
            ],
        }
    )
    sim = Simulator(CutTable.from_profile(profile), trace, seed=0)
    result = sim.run("elastic")
    state = result.extra["state"]
    hedged = float(result.hedged.mean())
    labels = [*result.actions, "P"]
    counts = np.bincount(result.column, minlength=len(labels))
    main = labels[int(np.argmax(counts))]
    other = 1.0 - float(counts[labels.index("0:jpeg50")]) / result.frames
    local_ms = float(np.median(full)) * MS / robot_cpu
    return {
        "size": f"{width}x{height}",
        "model": f"zoo:{MODEL}",
        "full_model_ms": _stats(full, MS),
        "jpeg50_encode_ms": _stats(encodes["jpeg50"], MS),
        "jpeg80_encode_ms": _stats(encodes["jpeg80"], MS),
        "elastic_decide_observe_us": _stats(decision, US),
        "static_decide_observe_us": _stats(static_decision, US),
        "sim": {
            "robot_cpu": robot_cpu,
            "uplink_mbit": uplink_mbit,
            "main_action": main,
            "hedged_per_100": round(100 * hedged, 2),
            "other_actions_per_100": round(100 * other, 2),
            "robot_probes": state["robot_probes"],
        },
        "extra_ms_per_frame_on_robot": {
            "decision": round(
                (float(np.median(decision)) - float(np.median(static_decision))) * MS / robot_cpu,
                4,
            ),
            "hedged_local_runs_upper": round(hedged * local_ms, 3),
            "other_codec_encodes": round(
                other * float(np.median(encodes["jpeg80"])) * MS / robot_cpu, 4
            ),
            "one_hedged_local_run": round(local_ms, 1),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--size", action="append", help="WxH (repeatable; default 224x224, 640x480)"
    )
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--robot-cpu", type=float, default=0.1)
    parser.add_argument("--uplink-mbit", type=float, default=12.0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = []
    for size in args.size or ["224x224", "640x480"]:
        width, height = (int(v) for v in size.split("x"))
        rows.append(measure(width, height, args.runs, args.robot_cpu, args.uplink_mbit))
    print(json.dumps(rows, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
