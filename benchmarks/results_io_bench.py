"""Frames in, results out: what the zenoh in/out path costs, and how a camera-rate sender fares.

A registry (the fleet's router) and one robot with `--source zenoh --policy robot` run as real
subprocesses on loopback; this process is the application, through
`robotd.results.client.RobotClient` (a Zenoh client of the router, as an application on another host
would be). The robot's telemetry (`tele/<robot>`) gives each frame's model time (`prefix_s`: the
whole model, P).

1. Overhead at 640×480: one frame at a time, a 640×480 camera frame from a real photograph sent
   as JPEG (encoded by the client, quality 90), the clock running from before the encoding to
   the result's arrival in the client. Overhead = that time - the frame's model time: JPEG
   encode and decode, the fit to the model's input, both Zenoh hops through the router, the
   robot's frame loop and the result's encoding and decoding; also without the client's JPEG
   encoding (a camera that gives JPEG). Target: median <= 2 ms.
2. A 30 fps sender against a robot that serves about 10 fps (the model stretched by
   `--robot-slowdown`, emulating a slower robot): for `--seconds` the client sends frames at 30
   fps; each result's age is its publication time minus the frame's capture stamp (one clock:
   one host). Bound: p95 age <= 2 frame periods + the serving time (the median model time).
   No growing queue: the age in the last third of the run against the first. Every frame sent
   is served or counted as dropped (`dropped_stale` in the robot's summary), at most one still
   waiting when the robot stops.

    python benchmarks/results_io_bench.py [--frames 200] [--seconds 20] [--json]
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.local_fleet import LocalFleet, write_local_fleet

ROBOT = "robot-1"
MODEL = "zoo:mobilenet_v2"
INPUT_SHAPE = [3, 224, 224]
CAMERA_H, CAMERA_W = 480, 640
SENDER_FPS = 30.0
TARGET_SERVE_FPS = 10.0
WAIT_S = 60.0
RESULT_TIMEOUT_S = 10.0
P95 = 95


def camera_frames(count: int) -> list[np.ndarray]:
    """`count` 640×480 views of a real photograph, each moved by a pixel."""
    from common.photos import photo_bgr

    photo = photo_bgr("astronaut")
    big = np.pad(photo, ((0, CAMERA_H), (0, CAMERA_W), (0, 0)), mode="reflect")
    return [np.ascontiguousarray(big[n : n + CAMERA_H, n : n + CAMERA_W]) for n in range(count)]


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def start(lf: LocalFleet, *args: str) -> Any:
    lf.start_registry()
    return lf.start_robot(
        ROBOT, "--source", "zenoh", "--policy", "robot", "--json", *args, wait=True
    )


def summary_of(robot: Any) -> dict[str, Any]:
    robot.stop(sig=signal.SIGINT)
    lines = [line for line in robot.log_text().splitlines() if line.startswith("{")]
    return json.loads(lines[-1])


def overhead(config: Path, workdir: Path, frames: int, mode: str = "client") -> dict[str, Any]:
    """Part 1: one frame at a time, JPEG 640×480, end to end minus the model's own time."""
    from common.wire.app_to_robot import FrameIn, image_in
    from robotd.results.client import RobotClient

    images = camera_frames(20)
    with LocalFleet(config, workdir, startup_timeout_s=WAIT_S) as lf:
        tap = lf.tap(ROBOT)
        robot = start(lf)
        samples: list[tuple[float, float, float]] = []  # (end to end, model, encode) seconds
        # Where the rest goes, from the result's stamps (one clock): the frame's way in (send,
        # the hop, decode and fit), the robot's loop around the model, the result's way out.
        parts: list[tuple[float, float, float]] = []
        with RobotClient(config, ROBOT, quality=90, mode=mode) as client:
            if not client.wait_for_robot(WAIT_S):
                raise SystemExit("the robot's zenoh source never subscribed")
            for n in range(frames + 10):  # the first 10 warm up
                t0 = time.perf_counter()
                image = image_in(images[n % len(images)], "jpeg", quality=90)
                encoded = time.perf_counter()
                stamp = client.send(FrameIn(stamp_ns=time.time_ns(), images={"image": image}))
                result = next(r for r in client.results(RESULT_TIMEOUT_S) if r.stamp_ns == stamp)
                elapsed = time.perf_counter() - t0
                record = tap.wait_for(
                    lambda r, f=result.frame: r["frame"] == f,
                    timeout_s=RESULT_TIMEOUT_S,
                    what=f"the telemetry of frame {result.frame}",
                )
                if n >= 10:
                    model_s = float(record["prefix_s"])
                    samples.append((elapsed, model_s, encoded - t0))
                    m = result.message
                    parts.append(
                        (
                            (m.published_ns - m.stamp_ns) / 1e9 - m.latency_s,
                            m.latency_s - model_s,
                            (result.received_ns - m.published_ns) / 1e9,
                        )
                    )
        summary = summary_of(robot)
    over = [e - m for e, m, _ in samples]
    return {
        "client_mode": mode,
        "frames": len(samples),
        "end_to_end_ms_median": 1000 * statistics.median(e for e, _, _ in samples),
        "model_ms_median": 1000 * statistics.median(m for _, m, _ in samples),
        "jpeg_encode_ms_median": 1000 * statistics.median(c for _, _, c in samples),
        "overhead_ms_median": 1000 * statistics.median(over),
        "overhead_ms_p95": 1000 * percentile(over, P95),
        # The same from the moment the JPEG is handed to the client (a camera gives JPEG).
        "overhead_after_encode_ms_median": 1000
        * statistics.median(e - m - c for e, m, c in samples),
        "in_path_ms_median": 1000 * statistics.median(p[0] for p in parts),
        "robot_loop_ms_median": 1000 * statistics.median(p[1] for p in parts),
        "out_path_ms_median": 1000 * statistics.median(p[2] for p in parts),
        "robot_frames": summary["frames"],
    }


def camera_rate(config: Path, workdir: Path, seconds: float, slowdown: float) -> dict[str, Any]:
    """Part 2: a 30 fps sender against a robot serving about 10 fps."""
    from common.wire.app_to_robot import FrameIn, image_in
    from robotd.results.client import RobotClient

    period_s = 1.0 / SENDER_FPS
    payloads = [image_in(f, "jpeg", quality=90) for f in camera_frames(30)]
    with LocalFleet(config, workdir, startup_timeout_s=WAIT_S) as lf:
        tap = lf.tap(ROBOT)
        robot = start(lf, "--robot-slowdown", f"{slowdown:g}")
        with RobotClient(config, ROBOT, max_queued=100_000) as client:
            if not client.wait_for_robot(WAIT_S):
                raise SystemExit("the robot's zenoh source never subscribed")
            stamps: list[int] = []
            stop = threading.Event()
            begin = time.perf_counter()
            n = 0
            # The sender: one frame every period, on schedule (no drift), for `seconds`.
            while (due := begin + n * period_s) < begin + seconds:
                wait = due - time.perf_counter()
                if wait > 0:
                    stop.wait(wait)
                image = payloads[n % len(payloads)]
                stamps.append(
                    client.send(FrameIn(stamp_ns=time.time_ns(), images={"image": image}))
                )
                n += 1
            results = []
            # Results until the newest frame's (the robot takes it last), bounded.
            for result in client.results(RESULT_TIMEOUT_S):
                results.append(result)
                if result.stamp_ns == stamps[-1]:
                    break
            dropped_client = client.dropped
        summary = summary_of(robot)
        records = tap.snapshot()
    ages = [(r.message.published_ns - r.stamp_ns) / 1e9 for r in results]
    # What a frame waited before the robot took it (and the hops): its age minus its own
    # serving time. The bound's 2 periods are about this part.
    waits = [age - r.latency_s for age, r in zip(ages, results, strict=True)]
    serving = statistics.median(float(r["prefix_s"]) for r in records)
    third = max(1, len(ages) // 3)
    bound = 2 * period_s + serving
    return {
        "seconds": seconds,
        "sent": len(stamps),
        "results": len(results),
        "robot_frames": summary["frames"],
        "dropped_stale": summary["dropped_stale"],
        "unaccounted": len(stamps) - summary["frames"] - summary["dropped_stale"],
        "client_queue_dropped": dropped_client,
        "serve_fps": summary["fps"],
        "serving_ms_median": 1000 * serving,
        "age_ms_median": 1000 * statistics.median(ages),
        "age_ms_p95": 1000 * percentile(ages, P95),
        "age_bound_ms": 1000 * bound,
        "serving_ms_p95": 1000 * percentile([float(r["prefix_s"]) for r in records], P95),
        "wait_ms_median": 1000 * statistics.median(waits),
        "wait_ms_p95": 1000 * percentile(waits, P95),
        "two_periods_ms": 2000 * period_s,
        "age_ms_p95_first_third": 1000 * percentile(ages[:third], P95),
        "age_ms_p95_last_third": 1000 * percentile(ages[-third:], P95),
        "wait_ms_p95_first_third": 1000 * percentile(waits[:third], P95),
        "wait_ms_p95_last_third": 1000 * percentile(waits[-third:], P95),
        "stamps_in_order": [r.stamp_ns for r in results] == sorted(r.stamp_ns for r in results),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        config = write_local_fleet(
            work,
            model=MODEL,
            changes={"input_shape": INPUT_SHAPE, "machines": {ROBOT: {"fps": None}}},
        )
        first = overhead(config, work / "overhead", args.frames)
        # The robot's own model time in part 1 sets the slowdown that makes it serve ~10 fps.
        slowdown = max(1.0, (1.0 / TARGET_SERVE_FPS) / (first["model_ms_median"] / 1000))
        out = {
            "model": MODEL,
            "input_shape": INPUT_SHAPE,
            "camera": f"{CAMERA_W}x{CAMERA_H}",
            "overhead": first,
            "overhead_peer": overhead(config, work / "overhead-peer", args.frames, "peer"),
            "camera_rate": {
                "robot_slowdown": slowdown,
                **camera_rate(config, work / "rate", args.seconds, slowdown),
            },
        }
    if args.json:
        print(json.dumps(out, indent=2))
        return
    for part, values in out.items():
        print(f"{part}: {values}")


if __name__ == "__main__":
    main()
