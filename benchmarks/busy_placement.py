"""Issue 12's placement experiment with real daemons: do robots refused `busy` find room?

One host, loopback, the commands a user runs: `elasticfog registry`, two `elasticfog cloud`
(edge-1 in service for every robot, edge-2 in standby; 2 workers each) and N
`elasticfog robot --policy cloud --fps 10 --frames 100 --telemetry FILE` (zoo:resnet at
3x240x320), all started together. When every robot has finished, its telemetry file gives per
frame whether the cloud served it, and if not why (`busy`, `timeout`...), which deployment
served it and the end-to-end latency. Printed per run: the fallback rate by reason, each
deployment's share of the served frames, the p95 latency, and the registry's route changes
by reason (from its log).

    python benchmarks/busy_placement.py [--robots 8,16] [--frames 100] [--fps 10] [--json]
        [--src DIR]

`--src DIR` puts DIR first on the daemons' import path (another revision's `registry/`, for a
side-by-side run).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import tempfile
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy.local_fleet import LocalFleet, write_local_fleet

CLOUDS = ("edge-1", "edge-2")
FINISH_TIMEOUT_S = 300.0
ROUTE_LINE = re.compile(r"route (\S+): (\S+) -> (\S+) \(epoch \d+, (\w+)\)")


def fleet_changes(robots: int, fps: float, workers: int) -> dict[str, Any]:
    """The issue's fleet: every robot in service on edge-1, edge-2 standby, policy cloud."""
    names = [f"robot-{i}" for i in range(1, robots + 1)]
    machines: dict[str, Any] = {
        c: {"role": "cloud", "listen": ["tcp/127.0.0.1:0"], "workers": workers} for c in CLOUDS
    }
    machines.update(
        {r: {"role": "robot", "listen": ["tcp/127.0.0.1:0"], "fps": fps} for r in names}
    )
    policy: dict[str, Any] = {r: "robot" for r in names}
    policy["edge-1"] = {r: "service" for r in names}
    policy["edge-2"] = {r: "standby" for r in names}
    return {
        "input_shape": [3, 240, 320],
        "policy": {"kind": "cloud"},
        "machines": machines,
        "initial_policy": policy,
    }


def summarize(records: list[dict[str, Any]], registry_log: str) -> dict[str, Any]:
    """Fallback rates by reason, share per deployment, p95 latency, route changes by reason."""
    n = len(records)
    fallbacks = Counter(str(r.get("reason")) for r in records if r.get("fallback"))
    served = Counter(
        str(r["deployment"]) for r in records if not r.get("fallback") and r.get("deployment")
    )
    local = sum(1 for r in records if not r.get("fallback") and not r.get("deployment"))
    latencies = sorted(float(r["latency_s"]) for r in records)
    p95 = statistics.quantiles(latencies, n=20)[-1] if len(latencies) >= 2 else None
    moves = Counter(m.group(4) for m in ROUTE_LINE.finditer(registry_log))
    total_served = sum(served.values())
    return {
        "frames": n,
        "fallback_rate": sum(fallbacks.values()) / n if n else None,
        "busy_rate": fallbacks.get("busy", 0) / n if n else None,
        "timeout_rate": fallbacks.get("timeout", 0) / n if n else None,
        "fallbacks": dict(fallbacks),
        "computed_locally": local,
        "served": dict(served),
        "share": {d: c / total_served for d, c in served.items()} if total_served else {},
        "p95_latency_s": p95,
        "route_changes": dict(moves),
    }


def run(
    robots: int, frames: int, fps: float, workers: int, workdir: Path, src: str | None
) -> dict[str, Any]:
    directory = workdir / f"r{robots}"
    path = write_local_fleet(
        directory,
        fleet=f"busy-{uuid.uuid4().hex[:8]}",
        model="zoo:resnet",
        changes=fleet_changes(robots, fps, workers),
    )
    env = None
    if src:
        path_ = os.pathsep.join(filter(None, [src, os.environ.get("PYTHONPATH")]))
        env = {**os.environ, "PYTHONPATH": path_}
    with LocalFleet(path, directory, env=env, startup_timeout_s=120.0) as lf:
        lf.start_registry()
        lf.start_clouds(list(CLOUDS))
        files = {f"robot-{i}": directory / f"robot-{i}.jsonl" for i in range(1, robots + 1)}
        procs = [
            lf.start_robot(r, "--policy", "cloud", frames=frames, telemetry=f)
            for r, f in files.items()
        ]
        deadline = time.monotonic() + FINISH_TIMEOUT_S
        for proc in procs:
            rc = proc.wait(max(1.0, deadline - time.monotonic()))
            if rc != 0:
                raise RuntimeError(f"{proc.name} exited {rc}:\n{proc.log_tail()}")
        registry_log = lf.procs.get("registry").log_text()
    records = [
        json.loads(line)
        for f in files.values()
        for line in f.read_text(encoding="utf-8").splitlines()
        if line.strip()
    ]
    return {"robots": robots, **summarize(records, registry_log)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="8,16", help="comma-separated robot counts")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--src", default=None, help="put DIR first on the daemons' import path")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="ef-busy-") as tmp:
        for robots in (int(x) for x in args.robots.split(",")):
            result = run(robots, args.frames, args.fps, args.workers, Path(tmp), args.src)
            results.append(result)
            if not args.json:
                print(json.dumps(result), flush=True)
    if args.json:
        print(json.dumps({"results": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
