"""One maneuver of the circuit in the in-process closed loop, frame by frame: d_coll in the
path's bin against the ground truth of the renderer's geometry (docs/navigation.md, "Why the
off-centre box was hit").

Each frame: the axle's distance ahead to what the path meets, the path bin's d_coll and its
ground truth (the nearest face point the left camera sees whose curvature rounds to that bin),
how many bins saw nothing (d_coll at the maximum range) where the ground truth has a face, and
what the assistant sent. Default: maneuver 2 (straight at the off-centre box), lap 0, a fixed
latency of 0.1 s, at 320×240 and 640×480; `--half-width 0` drives with the axle's path bin
alone (the paper's footprint, the assistant before the fix).

    python benchmarks/nav_offcentre.py [--size 640x480]... [--maneuver 2] [--lap 0]
        [--latency 0.1] [--half-width M] [--every 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from typing import Any

import numpy as np

from nav.closed_loop import DEFAULT_ROBOT_RADIUS_M, StereoPerception, run_maneuver
from nav.curvature import DEFAULT_MAX_RANGE_M, DcollProfile, arc_to_point
from nav.live_drive import maneuver_params
from nav.maneuvers import MANEUVERS_PER_LAP, circuit_lap
from nav.render import Pose
from nav.world import World

NEAR_M = 1.0
"""A bin that saw nothing counts as a miss when its ground truth is nearer than this (m)."""


def ground_truth(perception: StereoPerception, world: World, pose: Pose) -> np.ndarray:
    """d_coll per bin from the geometry: the face points the left camera's columns meet (the
    obstacle band is within every face's height), binned as the pipeline bins its points."""
    camera, bins = perception.camera, perception.pipeline.bins
    forward, right = pose.forward(), pose.right()
    axle = np.array([pose.x, pose.y])
    origin = axle + camera.forward_m * forward
    slopes = (np.arange(perception.renderer.width) - camera.cx_px) / camera.fx_px
    directions = forward[None, :] + slopes[:, None] * right[None, :]
    depth, _, _, _ = world.cast(origin, directions)
    seen = np.isfinite(depth)
    rel = origin + depth[seen, None] * directions[seen] - axle
    curvature, arc = arc_to_point(rel @ right, rel @ forward)
    index = bins.index(curvature)
    keep = (index >= 0) & (index <= bins.count - 1)
    out = np.full(bins.count, DEFAULT_MAX_RANGE_M)
    np.minimum.at(out, index[keep].astype(np.int64), np.minimum(arc[keep], DEFAULT_MAX_RANGE_M))
    return out


def drive(
    size: tuple[int, int], maneuver: int, lap: int, latency_s: float, half_width_m: float | None
) -> dict[str, Any]:
    """Drive the maneuver with the circuit's assistant (its half width replaced unless None);
    every frame's d_coll and truth kept."""
    perception = StereoPerception(size[0], size[1], threads=1)
    params = maneuver_params(perception.camera)
    if half_width_m is not None:
        params = replace(params, half_width_m=half_width_m)
    step = circuit_lap(lap)[maneuver]
    centre = perception.pipeline.bins.count // 2
    frames: list[dict[str, Any]] = []
    measured = perception.profile

    def profile(world: World, pose: Pose) -> DcollProfile:
        out = measured(world, pose)
        truth = ground_truth(perception, world, pose)
        empty = (out.distances >= DEFAULT_MAX_RANGE_M) & (truth < NEAR_M)
        frames.append(
            {
                "y_m": pose.y,
                "clearance_m": world.clearance(pose.x, pose.y) - DEFAULT_ROBOT_RADIUS_M,
                "path_dcoll_m": float(out.distances[centre]),
                "path_truth_m": float(truth[centre]),
                "bins_missed": int(empty.sum()),
            }
        )
        return out

    perception.profile = profile  # type: ignore[method-assign]
    started = time.perf_counter()
    result = run_maneuver(step.world, step.maneuver, perception, params=params, latency_s=latency_s)
    return {
        "size": f"{size[0]}x{size[1]}",
        "maneuver": step.maneuver.name,
        "lap": lap,
        "latency_s": latency_s,
        "stop_margin_m": params.stop_margin_m,
        "half_width_m": params.half_width_m,
        "min_depth_axle_m": perception.min_depth_m + perception.camera.forward_m,
        "collided": result.collided,
        "collision_s": result.collision_s,
        "min_clearance_m": result.min_clearance_m,
        "distance_m": result.distance_m,
        "frames": frames,
        "path_bin_empty_frames": sum(
            f["path_dcoll_m"] >= DEFAULT_MAX_RANGE_M and f["path_truth_m"] < NEAR_M for f in frames
        ),
        "wall_s": time.perf_counter() - started,
    }


def markdown(run: dict[str, Any], every: int) -> str:
    lines = [
        f"{run['size']} {run['maneuver']} (lap {run['lap']}, latency {run['latency_s']} s, stop "
        f"margin {run['stop_margin_m']:.2f} m, half width {run['half_width_m']:.2f} m, nearest "
        f"depth seen {run['min_depth_axle_m']:.3f} m "
        f"from the axle): collided {run['collided']} at {run['collision_s']}, min clearance "
        f"{run['min_clearance_m']:.3f} m, {run['distance_m']:.3f} m driven, path bin empty in "
        f"{run['path_bin_empty_frames']} of {len(run['frames'])} frames ({run['wall_s']:.0f} s)",
        "| frame | y (m) | clearance (m) | path d_coll (m) | path truth (m) | bins missed |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for i, f in enumerate(run["frames"]):
        if i % every and f["path_dcoll_m"] < DEFAULT_MAX_RANGE_M:
            continue  # every empty path bin is shown
        lines.append(
            f"| {i} | {f['y_m']:.3f} | {f['clearance_m']:.3f} | {f['path_dcoll_m']:.2f} | "
            f"{f['path_truth_m']:.2f} | {f['bins_missed']} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", action="append", help="WxH (repeatable; default both)")
    parser.add_argument(
        "--maneuver", default="2", help="index in the lap (0-6), or all: the seven in turn"
    )
    parser.add_argument("--lap", type=int, default=0)
    parser.add_argument("--latency", type=float, default=0.1, help="fixed latency, s")
    parser.add_argument("--every", type=int, default=2, help="table: every Nth frame")
    parser.add_argument(
        "--half-width",
        type=float,
        help="the assistant's half width, m (default: the circuit's; 0: the axle's path only)",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    runs = []
    maneuvers = range(MANEUVERS_PER_LAP) if args.maneuver == "all" else [int(args.maneuver)]
    for size in args.size or ["320x240", "640x480"]:
        width, height = (int(v) for v in size.split("x"))
        for maneuver in maneuvers:
            run = drive((width, height), maneuver, args.lap, args.latency, args.half_width)
            runs.append(run)
            if not args.json:  # as it comes: a 640×480 maneuver takes minutes
                print(markdown(run, args.every) + "\n", flush=True)
    if args.json:
        print(json.dumps(runs))


if __name__ == "__main__":
    main()
