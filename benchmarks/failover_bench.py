"""Failover time: SIGKILL the deployment serving a robot, time until another deployment answers.

One fleet on loopback (registry, edge-1, edge-2, robot-1 as real subprocesses, `deploy.procs`).
The robot offloads every frame (`--policy cloud`). Each run: wait until the serving deployment
has answered a few frames, SIGKILL it, and take the time from the kill (wall clock here) to the
completion of the first frame answered by the other deployment (wall clock in the robot's
telemetry, same host). The killed daemon is then started again and, once the registry lists it
as alive (standby), the next run kills whichever serves now. Frames lost are counted over the
whole run from the robot's telemetry (the runtime promises 0).

    python benchmarks/failover_bench.py [--runs 10] [--fps 30] [--input-shape 3x240x320] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.demo import answered_by, read_telemetry, summarize
from deploy.demo_summary import answered_since
from deploy.local_fleet import LocalFleet, write_local_fleet

ROBOT = "robot-1"
CLOUDS = ("edge-1", "edge-2")
WAIT_S = 30.0
FRAMES_BEFORE_KILL = 10
TARGET_MEDIAN_MS = 300.0


def run(runs: int, fps: float, input_shape: list[int], model: str, workdir: Path) -> dict[str, Any]:
    from common.partition import load_partition

    config = write_local_fleet(
        workdir,
        model=model,
        changes={"input_shape": input_shape, "machines": {ROBOT: {"fps": fps}}},
    )
    load_partition(model, input_shape=tuple(input_shape))  # warm cache: daemons only load it
    telemetry = workdir / "robot-1.jsonl"
    samples: list[dict[str, Any]] = []
    with LocalFleet(config, workdir) as lf:
        lf.start_registry()
        lf.start_clouds(list(CLOUDS))
        tap = lf.tap(ROBOT)
        robot = lf.start_robot(ROBOT, "--policy", "cloud", telemetry=telemetry)
        serving = "edge-1"
        for i in range(runs):
            standby = CLOUDS[1] if serving == CLOUDS[0] else CLOUDS[0]
            first = tap.wait_for(
                answered_since(serving), timeout_s=WAIT_S, what=f"{serving} serving", procs=[robot]
            )
            tap.wait_for(
                answered_since(serving, from_frame=int(first["frame"]) + FRAMES_BEFORE_KILL),
                timeout_s=WAIT_S,
                what=f"{FRAMES_BEFORE_KILL} frames answered by {serving}",
                procs=[robot],
            )
            killed_at = lf.kill(serving)
            took_over = tap.wait_for(
                answered_since(standby, after=killed_at),
                timeout_s=WAIT_S,
                what=f"{standby} answering after {serving} was killed",
                procs=[robot],
            )
            between = [
                r for r in tap.snapshot() if r["at"] >= killed_at and r["at"] <= took_over["at"]
            ]
            ms = (took_over["at"] - killed_at) * 1000.0
            samples.append(
                {
                    "run": i,
                    "killed": serving,
                    "to": standby,
                    "ms": round(ms, 1),
                    "frames_finished_locally": sum(1 for r in between if answered_by(r) is None),
                }
            )
            print(f"run {i}: killed {serving} -> {standby} in {ms:.0f} ms", file=sys.stderr)
            lf.start_cloud(serving)
            lf.wait_clouds([serving])
            serving = standby
        stop = robot.stop()
        if stop.returncode != 0:  # the figures stand; say how the robot ended
            print(f"robot exited with {stop.returncode}:\n{robot.log_tail()}", file=sys.stderr)
    records = read_telemetry(telemetry)
    frames = max((int(r["frame"]) for r in records), default=-1) + 1
    summary, reasons = summarize(records, frames)
    values = [s["ms"] for s in samples]
    return {
        "runs": samples,
        "median_ms": statistics.median(values),
        "min_ms": min(values),
        "max_ms": max(values),
        "target_median_ms": TARGET_MEDIAN_MS,
        "frames": frames,
        "lost": summary["lost"],
        "fallbacks": summary["fallbacks"],
        "fallback_reasons": reasons,
        "robot_exit": stop.returncode,
        "fps": fps,
        "input_shape": input_shape,
        "model": model,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--input-shape", default="3x240x320")
    parser.add_argument("--model", default="zoo:vgg")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    shape = [int(d) for d in args.input_shape.split("x")]
    with tempfile.TemporaryDirectory(prefix="elasticfog-failover-") as tmp:
        result = run(args.runs, args.fps, shape, args.model, Path(tmp))
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"model {args.model} {args.input_shape}, robot at {args.fps:g} fps, policy cloud\n")
    print("| run | killed | to | failover ms | frames finished locally meanwhile |")
    print("| ---: | --- | --- | ---: | ---: |")
    for s in result["runs"]:
        print(f"| {s['run']} | {s['killed']} | {s['to']} | {s['ms']:.0f} | "
              f"{s['frames_finished_locally']} |")  # fmt: skip
    print(
        f"\nmedian {result['median_ms']:.0f} ms (min {result['min_ms']:.0f}, max "
        f"{result['max_ms']:.0f}; target <= {TARGET_MEDIAN_MS:.0f}); frames {result['frames']}, "
        f"lost {result['lost']}, finished locally {result['fallbacks']} "
        f"{result['fallback_reasons']}"
    )


if __name__ == "__main__":
    main()
