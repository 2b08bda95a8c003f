"""Where `elastic`'s robot CPU per frame beyond a static policy of the same action comes from.

Against `cloud:jpeg50` (every frame cut 0 as JPEG 50), an `elastic` robot that also settles on
`cut:0:jpeg50` spends robot CPU on:

- its decision: `decide` + `observe` per frame (a static policy's are a table lookup);
- local runs of the whole model: an exploring frame (forced, or won by its confidence bonus),
  every offloaded frame of an update period and a robot probe are hedged, and the hedged local
  run (deferred while the reply is expected first, stopped when the reply comes) can run the
  whole model on the robot;
- other actions: a forced sample of another (cut, codec) encodes the frame again or runs a prefix;
  a frame served by P runs the whole model.

Each part is timed alone here as process CPU time (one onnxruntime thread, so wall time on an
idle core), median and p95 of `--runs`, for zoo:mobilenet_v2 at each `--size`. Then `elastic`
is replayed frame by frame on a trace where cut 0 wins throughout (a robot at `--robot-cpu` of
this host on `--uplink-mbit`, the §5 setting: 0.1 core, 12 Mbit/s; the simulator's cost model,
the model's own profile at that size), each frame charged the robot CPU it would take: the
decision as timed; an encode; a hedged local run in full when it beats the reply, else the CPU
the robot's share of a core gives it from its start to the reply (an upper bound: at the lowest
priority it gets less); a P frame the whole model. The replay reports that CPU back to the policy
(`Outcome.cpu_s`, as the robot daemon does), so the probes are priced as on a robot. Per frame,
the CPU beyond the static policy's (`extra`): median, p95, mean, and by source (how many frames
per 100, and their share of the frames above 1 ms).

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
from robotd.policies import PURE_ROBOT, FrameContext, Outcome, make_policy
from robotd.policies.base import CutTable
from robotd.sim.simulator import Simulator
from robotd.sim.trace import trace_from_dict

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
        p.observe(d, Outcome(prefix_s=0.0, cloud_s=0.02, bytes_up=int(jpeg["jpeg50"][0])))
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
    cuts = CutTable.from_profile(profile)
    sim = Simulator(cuts, trace, seed=0)
    costs = CpuCosts(
        full_s=float(np.median(full)),
        encode_s={c: float(np.median(e)) for c, e in encodes.items()},
        decision_s=decision,
        static_decision_s=float(np.median(static_decision)),
        robot_cpu=robot_cpu,
    )
    replay = _replay(sim, cuts, costs, report_cpu=True)
    unpriced = _replay(sim, cuts, costs, report_cpu=False)
    return {
        "size": f"{width}x{height}",
        "model": f"zoo:{MODEL}",
        "full_model_ms": _stats(full, MS),
        "jpeg50_encode_ms": _stats(encodes["jpeg50"], MS),
        "jpeg80_encode_ms": _stats(encodes["jpeg80"], MS),
        "elastic_decide_observe_us": _stats(decision, US),
        "static_decide_observe_us": _stats(static_decision, US),
        "one_hedged_local_run_on_robot_ms": round(float(np.median(full)) * MS / robot_cpu, 1),
        "replay": {"robot_cpu": robot_cpu, "uplink_mbit": uplink_mbit, **replay},
        # The same, the robot's CPU not reported to the policy: probes are not priced (as
        # before they were counted in the objective).
        "replay_unpriced": unpriced,
    }


class CpuCosts:
    """Robot CPU seconds of each part of a frame, as timed above."""

    def __init__(
        self,
        full_s: float,
        encode_s: dict[str, float],
        decision_s: np.ndarray,
        static_decision_s: float,
        robot_cpu: float,
    ) -> None:
        self.full_s = full_s
        self.encode_s = encode_s
        self.decision_s = decision_s
        self.static_decision_s = static_decision_s
        self.robot_cpu = robot_cpu


def _replay(sim: Simulator, cuts: CutTable, costs: CpuCosts, report_cpu: bool) -> dict[str, Any]:
    """Replay `elastic` frame by frame and charge each frame its robot CPU (module docstring);
    `report_cpu`: tell the policy (`Outcome.cpu_s`), as the robot daemon does."""
    policy = make_policy("elastic", cuts)
    seg = sim.segments[0]
    fr, fu, fc, fd = (f.tolist() for f in sim.factors)
    position = cuts.positions()
    static_cpu = costs.encode_s["jpeg50"] + costs.static_decision_s
    extra = np.empty(FRAMES)
    source: list[str] = []
    actions: dict[str, int] = {}
    decisions = costs.decision_s
    for t in range(FRAMES):
        d = policy.decide(FrameContext(t, 0.5))
        cpu = float(decisions[t % decisions.size])
        label = "P" if d.action == PURE_ROBOT else f"{d.action}:{d.codec}"
        actions[label] = actions.get(label, 0) + 1
        if d.action == PURE_ROBOT:
            lat = seg.full_s * fr[t]
            cpu += costs.full_s
            policy.observe(
                d, Outcome(prefix_s=lat, latency_s=lat, cpu_s=cpu if report_cpu else None)
            )
            extra[t] = cpu - static_cpu
            source.append("P frame")
            continue
        j = position[(int(d.action), d.codec, d.end)]
        cpu += costs.encode_s.get(str(d.codec), 0.0)
        y = seg.uplink_s[j] * fu[t] + seg.compute_s[j] * fc[t] + seg.downlink_s[j] * fd[t]
        local = seg.local_s[j] * fr[t]
        local_s = None
        why = "other action" if label != "0:jpeg50" else "none"
        if d.hedge:
            after = d.hedge_after_s
            if after + local <= y:  # the local run wins: it ran the whole model
                cpu += costs.full_s
                local_s = local
            else:  # stopped at the reply: the robot's share of a core until then
                cpu += min(costs.full_s, max(0.0, y - after) * costs.robot_cpu)
            if d.updating:
                why = "hedge: update period"
            elif d.forced:
                why = "hedge: forced sample"
            elif after <= 0.0 and not d.local_expected:
                why = "hedge: robot probe"
            else:
                why = "hedge: exploration"
        policy.observe(
            d,
            Outcome(
                prefix_s=0.0,
                cloud_s=y,
                bytes_up=int(cuts.bytes[j]),
                local_s=local_s,
                cpu_s=cpu if report_cpu else None,
            ),
        )
        extra[t] = cpu - static_cpu
        source.append(why)
    big = extra > 1e-3
    by_source = {}
    for name in sorted(set(source)):
        mask = np.array([s == name for s in source])
        by_source[name] = {
            "per_100_frames": round(100 * float(mask.mean()), 2),
            "share_of_frames_over_1ms": round(
                float((mask & big).sum()) / max(int(big.sum()), 1), 3
            ),
            "extra_ms_median": round(float(np.median(extra[mask])) * MS, 3),
        }
    state = policy.state()
    return {
        "frames": FRAMES,
        "actions": actions,
        "extra_cpu_ms_per_frame": {
            "median": round(float(np.median(extra)) * MS, 4),
            "p95": round(float(np.percentile(extra, 95)) * MS, 3),
            "mean": round(float(extra.mean()) * MS, 3),
        },
        "after_frame_300": {
            "median": round(float(np.median(extra[300:])) * MS, 4),
            "p95": round(float(np.percentile(extra[300:], 95)) * MS, 3),
        },
        "by_source": by_source,
        "robot_probes_lost": state["robot_probes_lost"],
        "probe_interval_frames": state["robot_probe_interval"],
        "update_periods": state["update_periods"],
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
