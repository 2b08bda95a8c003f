"""AprilTag 36h11 pose accuracy and rate of the shipped handler `perception.apriltag:detect` at
640x480 (FogROS2-LS's AprilTag workload), beside OpenCV's own corner refinements.

Frames are rendered (`perception.tag_scenes`, nothing is downloaded): one 0.16 m tag per frame
at a pose drawn at random (seeded) with its centre 0.5-2 m away, anywhere in view, any roll,
tilted up to 50°, on scikit-image's photographs in turn, with a Gaussian blur of 0.6 px and
pixel noise of 2 grey levels; intrinsics fx = fy = 600, centre (319.5, 239.5). The error of a
found pose is the distance between the found and the true centre (cm) and the angle of the
rotation between the found and the true orientation (degrees); a frame whose tag is not found
counts as missed, not in the errors. Rows:

- `elasticfog`: the handler (ArUco 3 candidates, corners fitted from the tag's sides, IPPE).
- `elasticfog, jpeg<Q> frames`: the same on the frames through the wire codec `jpeg<Q>` (the image
  a deployment gets at cut 0 with that codec; the coding is not timed).
- `OpenCV <refinement>`: OpenCV's classic detector with its own corner refinement, the same
  pose solver (`perception.apriltag.solve_pose`).
- `OpenCV, no refinement` and `OpenCV ArUco 3, no refinement`: the classic detector's corners,
  and those the handler starts from (ArUco 3's candidate search).

Time: the median per-frame time (grey conversion, detection, refinement and pose; not the
rendering) over `--calls` calls cycling through the frames, on one core (the process pinned to
one CPU, OpenCV on one thread): the calling thread's CPU time, which other processes on a shared
host do not inflate, and the wall time beside it; Hz is the inverse of the CPU time.

    python benchmarks/apriltag_pose.py [--frames 100] [--calls 300] [--jpeg 90] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from common.photos import PHOTOS
from common.wire.tensor_codecs import decode_encoded, encode_tensor_as
from perception.apriltag import TagParams, detect, outputs, solve_pose
from perception.tag_scenes import (
    TagPose,
    background,
    camera_matrix,
    pose_errors,
    random_pose,
    render,
)

HEIGHT, WIDTH = 480, 640
SIZE_M = 0.16
INTRINSICS = {"fx": 600.0, "fy": 600.0, "cx": 319.5, "cy": 239.5}
DISTANCE_M = (0.5, 2.0)
MAX_TILT_DEG = 50.0
BLUR_SIGMA_PX = 0.6
NOISE_SIGMA = 2.0
SEED = 7
TAG_IDS = 587
"""36h11 has 587 ids; the frames take them in turn."""

Detector = Callable[[np.ndarray], dict[str, np.ndarray]]


def frames(count: int) -> list[tuple[int, TagPose, np.ndarray]]:
    """`count` rendered frames: (tag id, true pose, uint8 1xHxWx3 RGB)."""
    rng = np.random.default_rng(SEED)
    k = camera_matrix(**INTRINSICS)
    scenes = [background(HEIGHT, WIDTH, name) for name in PHOTOS]
    out = []
    for i in range(count):
        pose = random_pose(rng, SIZE_M, k, HEIGHT, WIDTH, DISTANCE_M, MAX_TILT_DEG)
        tag_id = (i * 37) % TAG_IDS
        image = render(
            scenes[i % len(scenes)],
            [(tag_id, pose)],
            SIZE_M,
            k,
            blur_sigma_px=BLUR_SIGMA_PX,
            noise_sigma=NOISE_SIGMA,
            seed=SEED + i,
        )
        out.append((tag_id, pose, image[None]))
    return out


def handler() -> Detector:
    return lambda image: detect({"image": image}, size_m=SIZE_M, **INTRINSICS)


def through_codec(
    data: list[tuple[int, TagPose, np.ndarray]], codec: str
) -> list[tuple[int, TagPose, np.ndarray]]:
    """The frames as a deployment decodes them from the wire codec `codec` (cut 0)."""
    return [
        (tag_id, pose, decode_encoded(encode_tensor_as(image, codec), max_bytes=image.nbytes))
        for tag_id, pose, image in data
    ]


def opencv(refinement: int | None, aruco3: bool = False) -> Detector:
    """OpenCV's detector with its corner refinement `refinement` (None: none), then the same
    pose solver as the handler's."""
    parameters = cv2.aruco.DetectorParameters()
    parameters.useAruco3Detection = aruco3
    parameters.cornerRefinementMethod = (
        cv2.aruco.CORNER_REFINE_NONE if refinement is None else refinement
    )
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), parameters
    )
    tag = TagParams.parse({"size_m": SIZE_M, **INTRINSICS}, HEIGHT, WIDTH)

    def run(image: np.ndarray) -> dict[str, np.ndarray]:
        gray = cv2.cvtColor(image[0], cv2.COLOR_RGB2GRAY)
        corners, ids, _ = detector.detectMarkers(gray)
        flat = np.asarray(ids if ids is not None else [], dtype=np.int64).reshape(-1)
        found = [(int(flat[i]), np.asarray(corners[i]).reshape(4, 2)) for i in range(len(flat))]
        poses = [(i, c, solve_pose(c, tag)) for i, c in found]
        kept = [(i, c, p) for i, c, p in poses if p is not None]
        return outputs([i for i, _, _ in kept], [p for _, _, p in kept], [c for _, c, _ in kept])

    return run


def measure(
    name: str, run: Detector, data: list[tuple[int, TagPose, np.ndarray]], calls: int
) -> dict[str, Any]:
    translation_cm, rotation_deg, missed = [], [], 0
    for tag_id, pose, image in data:
        found = run(image)
        rows = np.flatnonzero(found["ids"] == tag_id)
        if len(rows) != 1:
            missed += 1
            continue
        t, r = pose_errors(found["poses"][rows[0]], pose)
        translation_cm.append(100 * t)
        rotation_deg.append(r)
    cpu, wall = [], []
    for i in range(calls):
        image = data[i % len(data)][2]
        start_cpu, start_wall = time.thread_time(), time.perf_counter()
        run(image)
        cpu.append(time.thread_time() - start_cpu)
        wall.append(time.perf_counter() - start_wall)
    ms = 1000 * statistics.median(cpu)
    return {
        "method": name,
        "found": len(data) - missed,
        "frames": len(data),
        "t_median_cm": statistics.median(translation_cm) if translation_cm else None,
        "t_max_cm": max(translation_cm, default=None),
        "r_median_deg": statistics.median(rotation_deg) if rotation_deg else None,
        "r_max_deg": max(rotation_deg, default=None),
        "cpu_ms_median": ms,
        "wall_ms_median": 1000 * statistics.median(wall),
        "hz": 1000 / ms,
    }


def _cpu() -> str:
    """The CPU's model name (Linux), else the machine type."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def _fmt(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| method | found | translation median / max (cm) | rotation median / max (°) "
        "| CPU ms/frame | wall ms/frame | Hz |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['found']}/{r['frames']} "
            f"| {_fmt(r['t_median_cm'], 2)} / {_fmt(r['t_max_cm'], 2)} "
            f"| {_fmt(r['r_median_deg'], 2)} / {_fmt(r['r_max_deg'], 2)} "
            f"| {r['cpu_ms_median']:.1f} | {r['wall_ms_median']:.1f} | {r['hz']:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=100, help="rendered poses")
    parser.add_argument("--calls", type=int, default=300, help="timed calls per method")
    parser.add_argument("--jpeg", type=int, default=90, help="quality of the jpeg row")
    parser.add_argument("--json", action="store_true", help="print JSON rows, not a table")
    args = parser.parse_args()

    # One core: the process on one CPU, OpenCV without its thread pool.
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    cv2.setNumThreads(1)

    data = frames(args.frames)
    jpeg = through_codec(data, f"jpeg{args.jpeg}")
    methods: list[tuple[str, Detector, list[tuple[int, TagPose, np.ndarray]]]] = [
        ("elasticfog", handler(), data),
        (f"elasticfog, jpeg{args.jpeg} frames", handler(), jpeg),
        ("OpenCV CORNER_REFINE_SUBPIX", opencv(cv2.aruco.CORNER_REFINE_SUBPIX), data),
        ("OpenCV CORNER_REFINE_CONTOUR", opencv(cv2.aruco.CORNER_REFINE_CONTOUR), data),
        ("OpenCV CORNER_REFINE_APRILTAG", opencv(cv2.aruco.CORNER_REFINE_APRILTAG), data),
        ("OpenCV, no refinement", opencv(None), data),
        ("OpenCV ArUco 3, no refinement", opencv(None, aruco3=True), data),
    ]
    for _, run, _ in methods:  # warm-up: first calls build tables and thread-local detectors
        run(data[0][2])
    rows = [measure(name, run, frames_, args.calls) for name, run, frames_ in methods]
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(
        f"{args.frames} rendered 640x480 frames, one {SIZE_M} m tag each at "
        f"{DISTANCE_M[0]}-{DISTANCE_M[1]} m, tilt <= {MAX_TILT_DEG:.0f}°; "
        f"{args.calls} timed calls per method on one core; OpenCV {cv2.__version__}, "
        f"{_cpu()}"
    )
    print()
    print(table(rows))


if __name__ == "__main__":
    main()
