"""Can a cut in the middle of a model pay, at any uplink? The lower envelope of the actions.

A robot's frame costs, for action (cut k, codec c) at uplink B,

    t(k, c, B) = s·prefix_k + encode_c·s + cloud_k + decode_c + bytes(k, c) / B

and s·full for P, with s the robot's slowdown against the profiling host (1 / --robot-cpu
cores), the cloud as fast as the profiling host, and round trips left out (they only add to
every offloading action). Every action is a line in 1/B, so the best action at each uplink is
the lower envelope of the lines. This measures the lines as the robot would (`robot_profile`,
codec entries measured on calibration frames of the `photo` source, lossy codecs on feature maps
allowed when they keep the answers: `min_top1_agreement`), then reports, for every action, the
uplinks where it is the best of all, and for each cut the most it ever beats both the best cut-0
action and P by (a middle cut "pays" at 1.2x).

    python benchmarks/middle_cuts.py [--model zoo:mobilenet_v2] [--input-shape 3x240x320]
                                     [--robot-cpu 0.5] [--frames 8] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from common.codec_profile import Fidelity, profile_codecs
from common.image_input import ImageInputs
from common.partition import load_partition, sample_feeds
from common.partition.runtime import SplitModel
from common.zoo import parse_shape
from robotd.calibration import calibration_frames
from robotd.daemon import robot_profile
from robotd.policies.base import PURE_ROBOT, CutTable

PAYS = 1.2
BITS_PER_BYTE = 8.0
# Uplinks scanned, Mbit/s (log-spaced): from a congested radio link to a wired LAN.
UPLINKS_MBIT = np.logspace(math.log10(0.05), math.log10(1000.0), 2001)


def measure(model_spec: str, shape: tuple[int, ...], frames: int, seed: int) -> dict[str, Any]:
    """The robot's profile of `model_spec` with every codec entry measured (all, not only the
    actions a bound admits: the analysis wants the smallest crossing each cut can have)."""
    partition = load_partition(model_spec, "auto", 2, shape)
    model = SplitModel(partition, threads=1)
    specs = model.input_specs()
    calib = calibration_frames("photo", ImageInputs(specs, model_spec), frames, seed)
    fidelity = Fidelity(lossy_features=True)
    codecs = profile_codecs(model, calib, fidelity)
    for entries in codecs.values():
        for e in entries:  # every codec that keeps the answers, not only the best 4 of a cut
            e["action"] = not e["lossy"] or fidelity.admits(
                e["top1_agreement"], e["rel_err"], e.get("bad_pixel_share")
            )
    return robot_profile(model, sample_feeds(specs), codecs=codecs)


def envelope(table: CutTable, slowdown: float) -> dict[str, Any]:
    """Per action, the uplinks where it is the best; per cut, its best ratio against both the
    best cut-0 action and P."""
    inv_b = BITS_PER_BYTE / (UPLINKS_MBIT * 1e6)  # seconds per byte at each uplink
    fixed = slowdown * table.prefix_s + table.cloud_s
    times = fixed[:, None] + table.bytes[:, None] * inv_b[None, :]  # actions x uplinks
    p_time = slowdown * table.full_s
    labels = table.labels[:-1]
    winners: dict[str, list[float]] = {}
    for u, uplink in enumerate(UPLINKS_MBIT):
        j = int(times[:, u].argmin())
        label = labels[j] if times[j, u] < p_time else PURE_ROBOT
        winners.setdefault(label, []).append(float(uplink))
    first = min(table.indices)
    cut0 = np.array([i == first for i in table.indices])
    rival = np.minimum(times[cut0].min(axis=0), p_time)  # the best of cut 0 and P
    cuts: list[dict[str, Any]] = []
    for index in sorted(set(table.indices)):
        rows = [j for j, i in enumerate(table.indices) if i == index]
        mine = times[rows].min(axis=0)
        ratio = rival / mine
        u = int(ratio.argmax())
        j = rows[int(times[rows, u].argmin())]
        cuts.append(
            {
                "cut": index,
                "robot_share": float(table.prefix_s[rows[0]] / table.full_s),
                "smallest_bytes": float(table.bytes[rows].min()),
                "smallest_codec": table.codecs[rows[int(table.bytes[rows].argmin())]],
                "best_ratio": float(ratio[u]),
                "at_uplink_mbit": float(UPLINKS_MBIT[u]),
                "with_codec": table.codecs[j],
            }
        )
    return {
        "p_time_s": p_time,
        "winners": {k: [min(v), max(v)] for k, v in winners.items()},
        "cuts": cuts,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="zoo:mobilenet_v2")
    parser.add_argument("--input-shape", default="3x240x320", help="CxHxW of the camera image")
    parser.add_argument("--robot-cpu", type=float, default=0.5, help="robot cores (slowdown 1/x)")
    parser.add_argument("--frames", type=int, default=8, help="calibration frames")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args()
    if not 0 < args.robot_cpu <= 16 or args.frames < 1:
        parser.error("--robot-cpu must be in (0, 16] and --frames >= 1")
    profile = measure(args.model, parse_shape(args.input_shape), args.frames, args.seed)
    table = CutTable.from_profile(profile)
    result = envelope(table, 1.0 / args.robot_cpu)
    result["settings"] = vars(args)
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"{args.model} {args.input_shape}, robot at {args.robot_cpu:g} core "
        f"(P {result['p_time_s'] * 1000:.1f} ms), {len(table.labels) - 1} (cut, codec) lines\n"
    )
    print("| best action | from (Mbit/s) | to (Mbit/s) |\n|---|---:|---:|")
    for label, (lo, hi) in sorted(result["winners"].items(), key=lambda kv: kv[1][0]):
        print(f"| {label} | {lo:.3g} | {hi:.3g} |")
    print(
        "\n| cut | robot share of the model | smallest crossing (codec) | best ratio vs "
        "min(cut 0, P) | at (Mbit/s) |\n|---:|---:|---|---:|---:|"
    )
    for c in result["cuts"]:
        print(
            f"| {c['cut']} | {c['robot_share']:.1%} | {c['smallest_bytes'] / 1000:.1f} KB "
            f"({c['smallest_codec']}) | {c['best_ratio']:.2f} | {c['at_uplink_mbit']:.3g} |"
        )
    best = max(result["cuts"][1:], key=lambda c: c["best_ratio"], default=None)
    if best is not None:
        verdict = "pays" if best["best_ratio"] >= PAYS else "never pays"
        print(
            f"\nbest middle cut: {best['cut']} ({best['with_codec']}) at "
            f"{best['at_uplink_mbit']:.3g} Mbit/s, {best['best_ratio']:.2f}x the best of cut 0 "
            f"and P: a middle cut {verdict} (>= {PAYS}x needed)"
        )


if __name__ == "__main__":
    main()
