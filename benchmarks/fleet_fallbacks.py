"""Issue 26's many-robot experiment as a user runs it, and where each fallback's time went.

A fleet from `elasticfog init DIR --robots N`, edited as a user would (both deployments with
`--workers` workers, `policy: {kind: cloud}`, each cloud's Prometheus endpoint on), then the
daemons started by hand, here as subprocesses: `elasticfog registry`, `elasticfog cloud --id
edge-1`, `... --id edge-2` (waited for), and N `elasticfog robot --id robot-i --frames F
--telemetry FILE`, all started together. Loopback, no root; zoo:resnet at init's input shape.

While the robots run, a sampler reads every 0.5 s the CPU each group of daemons used (robots,
clouds, registry) and what the rest of the host used (busy time of all CPUs not accounted for by
them) and the hypervisor's steal. When every robot has finished, each cloud's /metrics is read
(requests by robot and outcome, queue and compute seconds) and the robots' telemetry files give,
per frame, whether it fell back and why, the robot's own time before the request left (`prefix_s`,
its CPU for the frame `robot_cpu_s`), the wait for the cloud (`transfer_s`: the whole wait when no
reply came) and, for a served frame, the deployment's queue + compute (`cloud_s`).

Printed (`--json`: the whole result): the fallback share and its reasons, split into frames before
every robot had started sending (start-up) and after; for each reason the median split of a
fallback's time; the served frames' split for comparison; the cores used by each group; the
registry's route changes by reason; and the clouds' own counts (a frame the cloud computed but
whose reply came after the robot's deadline is `ok` there and `timeout` at the robot).

    python benchmarks/fleet_fallbacks.py [--robots 16] [--workers 2] [--frames 150] [--fps 10]
        [--runs 1] [--workdir DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
import uuid
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import psutil
import yaml
from prometheus_client.parser import text_string_to_metric_families

from common.yaml_files import read_yaml
from deploy.local_fleet import LocalFleet
from deploy.procs import elasticfog_argv, free_tcp_port

CLOUDS = ("edge-1", "edge-2")
FINISH_TIMEOUT_S = 600.0
"""Longest a run's robots may take to finish their frames."""
SAMPLE_S = 0.5
"""How often the CPU sampler reads the processes and the host."""
SCRAPE_TIMEOUT_S = 5.0
ROUTE_LINE = re.compile(r"route \S+: \S+ -> \S+ \(epoch \d+, (\w+)\)")
"""A route change in the registry's log, its reason captured."""


def init_fleet(directory: Path, robots: int, workers: int, fps: float) -> Path:
    """`elasticfog init` as a user types it, then the user's edits to fleet.yaml."""
    directory.mkdir(parents=True, exist_ok=True)
    fleet = f"ff-{uuid.uuid4().hex[:8]}"
    port = free_tcp_port()
    argv = [*elasticfog_argv(), "init", str(directory), "--robots", str(robots)]
    argv += ["--port", str(port), "--fleet", fleet, "--force"]
    subprocess.run(
        argv,
        check=True,
        capture_output=True,
    )
    path = directory / "fleet.yaml"
    data = read_yaml(path)
    for cloud in CLOUDS:
        machine = data["machines"][cloud]
        machine["workers"] = workers
        machine["metrics"] = {"port": free_tcp_port()}
    for robot in (f"robot-{i}" for i in range(1, robots + 1)):
        data["machines"][robot]["fps"] = fps
    data["policy"] = {"kind": "cloud", "params": {}}
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


class CpuSampler:
    """Cores used per group of processes and by the rest of the host, every SAMPLE_S."""

    def __init__(self, groups: dict[str, list[int]]) -> None:
        self._procs = {g: [psutil.Process(p) for p in pids] for g, pids in groups.items()}
        self.samples: list[dict[str, float]] = []
        self._last: dict[int, float] = {}  # pid -> CPU seconds at its last reading
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="cpu-sampler", daemon=True)

    def _read(self) -> tuple[float, dict[str, float], float, float]:
        spent = {}
        for group, procs in self._procs.items():
            total = 0.0
            for proc in procs:
                try:
                    t = proc.cpu_times()
                    self._last[proc.pid] = t.user + t.system + t.children_user + t.children_system
                except psutil.NoSuchProcess:
                    pass  # a robot that finished: what it used up to its last reading stays
                total += self._last.get(proc.pid, 0.0)
            spent[group] = total
        cpu = psutil.cpu_times()
        busy = cpu.user + cpu.nice + cpu.system + cpu.irq + cpu.softirq
        return time.monotonic(), spent, busy, getattr(cpu, "steal", 0.0)

    def _loop(self) -> None:
        last = self._read()
        while not self._stop.wait(SAMPLE_S):
            now = self._read()
            dt = now[0] - last[0]
            row = {g: (now[1][g] - last[1][g]) / dt for g in now[1]}
            host = (now[2] - last[2]) / dt
            row["others"] = max(0.0, host - sum(row.values()))
            row["steal"] = (now[3] - last[3]) / dt
            row["at"] = time.time()
            row["dt"] = dt
            self.samples.append(row)
            last = now

    def __enter__(self) -> CpuSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2 * SAMPLE_S)


def scrape(port: int) -> dict[str, Any]:
    """A cloud's requests by outcome and its queue/compute sums and counts."""
    url = f"http://127.0.0.1:{port}/metrics"
    with urllib.request.urlopen(url, timeout=SCRAPE_TIMEOUT_S) as resp:
        text = resp.read().decode()
    outcomes: Counter[str] = Counter()
    sums: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name.endswith("cloud_inference_requests_total"):
                outcomes[s.labels["outcome"]] += int(s.value)
            for part in ("queue_duration", "compute_infer_duration"):
                if part in s.name and s.name.endswith(("_sum", "_count")):
                    sums[f"{part}_{s.name.rsplit('_', 1)[1]}"] = s.value
    mean = {
        f"mean_{p}_s": sums[f"{p}_sum"] / sums[f"{p}_count"]
        for p in ("queue_duration", "compute_infer_duration")
        if sums.get(f"{p}_count")
    }
    return {"outcomes": dict(outcomes), **mean}


def median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def split_of(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Median time of each part of these frames: the robot's before the request left, the wait
    (the network, and for a frame with no reply everything the cloud did), the cloud's own."""
    return {
        "frames": len(records),
        "prefix_s": median([r["prefix_s"] for r in records]),
        "robot_cpu_s": median([r["robot_cpu_s"] for r in records]),
        "transfer_s": median([r["transfer_s"] for r in records]),
        "cloud_s": median([r["cloud_s"] for r in records]),
        "latency_s": median([r["latency_s"] for r in records]),
    }


def analyse(
    records: list[dict[str, Any]], samples: list[dict[str, float]], registry_log: str
) -> dict[str, Any]:
    n = len(records)
    # Start-up ends when the last robot's first frame completed: before that, robot daemons
    # still loading take the host's CPU from the rest.
    first = defaultdict(lambda: float("inf"))
    for r in records:
        first[r["robot"]] = min(first[r["robot"]], r["at"])
    all_started = max(first.values()) if first else 0.0
    fallbacks = [r for r in records if r.get("fallback")]
    steady = [r for r in records if r["at"] > all_started]
    steady_fb = [r for r in steady if r.get("fallback")]
    by_reason: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in steady_fb:
        by_reason[str(r.get("reason"))].append(r)
    served = [r for r in steady if not r.get("fallback") and r.get("deployment")]
    moves = Counter(m.group(1) for m in ROUTE_LINE.finditer(registry_log))
    steady_samples = [s for s in samples if s["at"] > all_started]

    def cores(rows: list[dict[str, float]]) -> dict[str, float | None]:
        keys = ("robots", "clouds", "registry", "others", "steal")
        return {k: median([s[k] for s in rows]) for k in keys}

    steady_s = sum(s["dt"] for s in steady_samples)
    return {
        "frames": n,
        "fallback_rate": len(fallbacks) / n if n else None,
        "steady_s": steady_s,
        "steady_frames_per_s": len(steady) / steady_s if steady_s else None,
        "cpu_s": {g: sum(s[g] * s["dt"] for s in samples) for g in ("robots", "clouds")},
        "fallbacks": dict(Counter(str(r.get("reason")) for r in fallbacks)),
        "startup_s": all_started - min(first.values()) if first else None,
        "startup_frames": n - len(steady),
        "startup_fallbacks": len(fallbacks) - len(steady_fb),
        "steady_frames": len(steady),
        "steady_fallback_rate": len(steady_fb) / len(steady) if steady else None,
        "steady_fallbacks": {k: len(v) for k, v in by_reason.items()},
        "steady_fallback_split": {k: split_of(v) for k, v in by_reason.items()},
        "steady_served_split": split_of(served),
        "served_by": dict(Counter(str(r["deployment"]) for r in served)),
        "cores_startup": cores([s for s in samples if s["at"] <= all_started]),
        "cores_steady": cores(steady_samples),
        "route_changes": dict(moves),
    }


def run(args: argparse.Namespace, directory: Path) -> dict[str, Any]:
    path = init_fleet(directory, args.robots, args.workers, args.fps)
    ports = {c: read_yaml(path)["machines"][c]["metrics"]["port"] for c in CLOUDS}
    files = {f"robot-{i}": directory / f"robot-{i}.jsonl" for i in range(1, args.robots + 1)}
    with LocalFleet(path, directory, startup_timeout_s=120.0) as lf:
        registry = lf.start_registry()
        clouds = lf.start_clouds(list(CLOUDS))
        started = time.time()
        robots = [lf.start_robot(r, frames=args.frames, telemetry=f) for r, f in files.items()]
        groups = {
            "robots": [p.pid for p in robots],
            "clouds": [p.pid for p in clouds],
            "registry": [registry.pid],
        }
        with CpuSampler(groups) as sampler:
            deadline = time.monotonic() + FINISH_TIMEOUT_S
            for proc in robots:
                rc = proc.wait(max(1.0, deadline - time.monotonic()))
                if rc != 0:
                    raise RuntimeError(f"{proc.name} exited {rc}:\n{proc.log_tail()}")
        cloud_metrics = {c: scrape(p) for c, p in ports.items()}
        registry_log = registry.log_text()
    records = []
    for robot, f in files.items():
        for line in f.read_text(encoding="utf-8").splitlines():
            if line.strip():
                records.append({**json.loads(line), "robot": robot})
    result = analyse(records, sampler.samples, registry_log)
    result["robots"] = args.robots
    result["started_at_unix"] = started
    result["clouds"] = cloud_metrics
    ok = sum(c["outcomes"].get("ok", 0) for c in cloud_metrics.values())
    # What a frame costs each side: the clouds' CPU per request they computed, the robots' per
    # frame (its own part, and the whole model for a frame that fell back).
    result["cloud_cpu_s_per_computed"] = result["cpu_s"]["clouds"] / ok if ok else None
    result["robot_cpu_s_per_frame"] = result["cpu_s"]["robots"] / len(records) if records else None
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=None, help="keep the fleets' files here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="ef-fallbacks-") as tmp:
        base = args.workdir or Path(tmp)
        for i in range(args.runs):
            result = run(args, base / f"run{i + 1}")
            results.append(result)
            if not args.json:
                print(json.dumps(result), flush=True)
    if args.json:
        print(json.dumps({"results": results}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
