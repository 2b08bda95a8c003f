"""The frames a planned move costs: a robot moved back and forth between two deployments.

One fleet on loopback (registry, edge-1, edge-2, robot-1 as real subprocesses, `deploy.procs`),
the robot offloading every frame (`--policy cloud`). Each move: once the serving deployment has
answered a few frames, a `RerouteRequest` (as after three timeouts) makes the registry move the
robot to the other one, epoch-fenced and make-before-break (docs/registry.md); the move ends at
the first frame the other deployment answers. Counted per move from the robot's telemetry: the
frames sent from the request until then that the robot finished itself, by fallback reason, and
the time from the request to that first answer. A move that no frame confirms within `WAIT_S`
is counted as not taken (`stuck`): the robot's queries found no route to the new deployment and
the robot's reroute request sent it back (docs/registry.md, "A move and the robot's route").

    python benchmarks/move_gap.py [--moves 20] [--fps 30] [--input-shape 3x64x64] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.demo import answered_by
from deploy.demo_summary import answered_since
from deploy.local_fleet import LocalFleet, write_local_fleet
from deploy.procs import DaemonError

ROBOT = "robot-1"
CLOUDS = ("edge-1", "edge-2")
WAIT_S = 3.0
FRAMES_BEFORE_MOVE = 5
# As many consecutive timeouts as force a move at once (registry.scheduler).
FORCED_TIMEOUTS = 3


def _reroute(lf: LocalFleet, deployment: str) -> None:
    from common import keys
    from common.wire.registry import RerouteRequest
    from common.wire.telemetry import FallbackReason

    request = RerouteRequest(
        robot=ROBOT,
        deployment=deployment,
        epoch=0,
        reason=FallbackReason.TIMEOUT,
        consecutive_timeouts=FORCED_TIMEOUTS,
    )
    lf.query(keys.reg_reroute(lf.fleet), request.to_wire(), timeout_s=5.0)


def run(
    moves: int, fps: float, input_shape: list[int], model: str, workdir: Path
) -> dict[str, Any]:
    from common.partition import load_partition

    config = write_local_fleet(
        workdir,
        model=model,
        changes={"input_shape": input_shape, "machines": {ROBOT: {"fps": fps}}},
    )
    load_partition(model, input_shape=tuple(input_shape))  # warm cache: daemons only load it
    samples: list[dict[str, Any]] = []
    with LocalFleet(config, workdir) as lf:
        lf.start_registry()
        lf.start_clouds(list(CLOUDS))
        tap = lf.tap(ROBOT)
        robot = lf.start_robot(ROBOT, "--policy", "cloud", telemetry=workdir / "robot.jsonl")
        first = tap.wait_for(
            lambda r: answered_by(r) is not None,
            timeout_s=60.0,
            what="a served frame",
            procs=[robot],
        )
        serving = str(answered_by(first))
        for i in range(moves):
            other = CLOUDS[1] if serving == CLOUDS[0] else CLOUDS[0]
            start = time.time()
            for _ in range(FRAMES_BEFORE_MOVE):  # bounded: FRAMES_BEFORE_MOVE answered frames
                tap.wait_for(
                    answered_since(serving, after=time.time()),
                    timeout_s=WAIT_S,
                    what=serving,
                    procs=[robot],
                )
            asked_at = time.time()
            _reroute(lf, serving)
            try:
                moved = tap.wait_for(
                    answered_since(other, after=asked_at),
                    timeout_s=WAIT_S,
                    what=other,
                    procs=[robot],
                )
                done_at, stuck = float(moved["at"]), False
            except DaemonError:  # no frame answered by the other deployment: the move not taken
                done_at, stuck = time.time(), True
            between = [r for r in tap.snapshot() if asked_at <= float(r["at"]) <= done_at]
            reasons = Counter(str(r.get("reason")) for r in between if r.get("fallback"))
            answered = Counter(str(answered_by(r)) for r in between if answered_by(r))
            samples.append(
                {
                    "move": i,
                    "from": serving,
                    "to": other,
                    "ms": round((done_at - asked_at) * 1000.0, 1),
                    "stuck": stuck,
                    "fallbacks": dict(reasons),
                    "frames": len(between),
                    "answered": dict(answered),
                    "waited_s": round(asked_at - start, 2),
                }
            )
            print(f"move {i}: {serving} -> {other} {samples[-1]}", file=sys.stderr)
            if not stuck:
                serving = other
        robot.stop()
    ok = [s for s in samples if not s["stuck"]]
    per_move = [sum(s["fallbacks"].values()) for s in samples]
    return {
        "moves": samples,
        "stuck": sum(1 for s in samples if s["stuck"]),
        "fallbacks_per_move_median": statistics.median(per_move),
        "fallbacks_per_move_mean": round(statistics.fmean(per_move), 2),
        "fallbacks_per_move_max": max(per_move),
        "fallback_reasons": dict(sum((Counter(s["fallbacks"]) for s in samples), Counter())),
        "move_ms_median": statistics.median(s["ms"] for s in ok) if ok else None,
        "fps": fps,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=20)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--input-shape", default="3x64x64")
    parser.add_argument("--model", default="zoo:mobilenet")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    shape = [int(x) for x in args.input_shape.split("x")]
    with tempfile.TemporaryDirectory(prefix="move-gap-") as tmp:
        result = run(args.moves, args.fps, shape, args.model, Path(tmp))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        keys = ("stuck", "fallbacks_per_move_median", "fallbacks_per_move_mean")
        print({k: result[k] for k in (*keys, "fallbacks_per_move_max", "fallback_reasons")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
