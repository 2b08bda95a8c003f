"""Resident memory of a cloud daemon against its model's weight bytes and the runtime's baseline.

A cloud daemon keeps one warm onnxruntime suffix session per cut; the sessions share one copy of
the weights (`SplitModel`), so its memory should not grow with the number of cuts. The target
(issue 4): RSS with 16 cuts <= runtime baseline + 1.5 x the model's weight bytes.

Each figure is the resident set size (psutil RSS; the median of a few readings, then the median
over `--repeat` daemons, as malloc's high-water marks vary from run to run) of a real
`elasticfog cloud` subprocess once it is ready (liveliness token up, every suffix built and run
once), with this script's own router session standing in for the registry's:

- baseline: the daemon serving a model without weights (x -> Relu -> Neg -> y): Python, numpy,
  onnxruntime, Zenoh, the daemon's threads; everything but a model's weights;
- `zoo:resnet` at 3x240x320 (the fleet's default model; 5.6 MB of weights, so the baseline
  dominates) with 2, 8 and 16 cuts;
- a dense MatMul chain with 60 MiB of weights (15 layers of 1024x1024 float32), where the weights
  dominate, with 2, 8 and 16 cuts.

`--naive` also measures, per model, a plain process holding the 16 suffix sessions loaded the
default way (each `InferenceSession` reads its own copy of the weights): what sharing saves.
`--breakdown` shows, in one process, the RSS each step of loading a 16-cut model adds.

`--robot [FLEET.yaml]` measures the robot daemon instead: its start-up steps as the daemon takes
them (imports, the split model's sessions, the warm-up that runs every prefix and suffix once,
the profile and codec calibration, the trim of the freed heap, the source), then `--rounds`
rounds of frames, each running every action the robot may take (the whole model; each cut's
prefix, then its suffix as a fallback does) on a frame of the source: per step the RSS after it
and the peak during it, and each action's median time. Each run is a fresh interpreter, two
variants alternated `--pairs` times: `before` (every session, the segments' too, and the startup
runs' freed memory left in the heap) and `after` (as `elasticfog robot` starts now). Without a
file, the navigation benchmark's fleet (zoo:stereo with segments, `stereo:world` frames, one
onnxruntime thread) at each of `--resolutions` (`docs/robot.md`, Memory).

    python benchmarks/memory_bench.py [--naive] [--breakdown] [--repeat 3] [--json]
    python benchmarks/memory_bench.py --robot [FLEET] [--resolutions 320x240,640x480]
        [--rounds 3] [--pairs 1] [--robot-id robot-1] [--json]

Splits go to the model cache (`ELASTICFOG_CACHE_DIR`, else the user cache directory).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import onnx
import psutil
from onnx import TensorProto, helper, numpy_helper

from deploy.local_fleet import LocalFleet, write_local_fleet
from deploy.procs import free_tcp_port

MiB = 1024 * 1024
TARGET_RATIO = 1.5
TARGET_CUTS = 16
CUT_COUNTS = (2, 8, 16)
RSS_READINGS = 5
RSS_INTERVAL_S = 0.1
DENSE_LAYERS = 15
DENSE_DIM = 1024
RESNET_SHAPE = [3, 240, 320]
STARTUP_TIMEOUT_S = 120.0


@dataclass
class Row:
    """One measured daemon."""

    model: str
    cuts: int
    weight_bytes: int
    rss_bytes: int
    naive_rss_bytes: int | None = None
    breakdown: dict[str, int] | None = None


def _save(graph: onnx.GraphProto, path: Path) -> Path:
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    path.write_bytes(model.SerializeToString())
    return path


def weightless_model(path: Path) -> Path:
    """x[1,16] -> Relu -> Neg -> y: a model with no weights (the runtime's baseline)."""
    graph = helper.make_graph(
        [
            helper.make_node("Relu", ["x"], ["a"], name="a"),
            helper.make_node("Neg", ["a"], ["y"], name="y"),
        ],
        "weightless",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 16])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 16])],
    )
    return _save(graph, path)


def dense_model(path: Path) -> Path:
    """x[1,D] -> (MatMul -> Relu) x layers -> Identity: 16 cuts, weights dominate."""
    rng = np.random.default_rng(0)
    nodes, inits = [], []
    prev = "x"
    for i in range(DENSE_LAYERS):
        w = (rng.standard_normal((DENSE_DIM, DENSE_DIM)) / np.sqrt(DENSE_DIM)).astype(np.float32)
        inits.append(numpy_helper.from_array(w, f"W{i}"))
        nodes.append(helper.make_node("MatMul", [prev, f"W{i}"], [f"m{i}"], name=f"m{i}"))
        if i < DENSE_LAYERS - 1:
            nodes.append(helper.make_node("Relu", [f"m{i}"], [f"r{i}"], name=f"r{i}"))
            prev = f"r{i}"
    nodes.append(helper.make_node("Identity", [f"m{DENSE_LAYERS - 1}"], ["y"], name="y"))
    graph = helper.make_graph(
        nodes,
        "dense",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, DENSE_DIM])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, DENSE_DIM])],
        inits,
    )
    return _save(graph, path)


def cut_names(model: str, shape: list[int] | None, count: int) -> list[str] | None:
    """The first `count - 1` automatic cuts (cut 0 is always there), as fleet.yaml names them."""
    from common.partition import CUT_SEPARATOR, load_partition

    auto = load_partition(model, input_shape=tuple(shape) if shape else None)
    if len(auto.cuts) < count:
        raise SystemExit(f"{model} has only {len(auto.cuts)} cuts, {count} asked")
    return [CUT_SEPARATOR.join(c.tensors) for c in auto.cuts[1:count]]


def prepare(model: str, shape: list[int] | None, names: list[str] | None) -> tuple[int, Path, int]:
    """Split into the cache (so the daemon only loads it): weight bytes, split dir, cut count."""
    from common.partition import load_partition
    from common.partition.runtime import SharedWeights

    part = load_partition(model, names or "auto", input_shape=tuple(shape) if shape else None)
    return SharedWeights(part).nbytes, part.dir, len(part.cuts)


def measure_daemon(
    workdir: Path, model: str, shape: list[int] | None, names: list[str] | None
) -> int:
    """RSS of a ready `elasticfog cloud` serving `model` with the cuts `names`."""
    changes: dict[str, Any] = {"cuts": {"names": names}}
    if shape:
        changes["input_shape"] = shape
    workdir.mkdir(parents=True, exist_ok=True)
    config = write_local_fleet(workdir, model=model, port=free_tcp_port(), changes=changes)
    from common.config import load_fleet
    from common.session import open_session

    cfg = load_fleet(config)
    # This process is the router the daemon connects to (as the registry's would be).
    router = open_session(router=True, listen=[cfg.registry.endpoint])
    try:
        with LocalFleet(config, workdir, startup_timeout_s=STARTUP_TIMEOUT_S) as fleet:
            (proc,) = fleet.start_clouds(["edge-1"])
            process = psutil.Process(proc.pid)
            readings = []
            for _ in range(RSS_READINGS):
                readings.append(process.memory_info().rss)
                time.sleep(RSS_INTERVAL_S)  # spacing between readings, not a readiness wait
            result = proc.stop()
            if result.returncode != 0:
                raise SystemExit(f"edge-1 exited {result.returncode}:\n{proc.log_tail()}")
            return int(statistics.median(readings))
    finally:
        router.close()


def naive_child(split_dir: str) -> None:
    """(In a child process) hold every suffix session loaded the default way; print RSS."""
    import onnxruntime as ort

    from common.partition import Partition

    part = Partition.load(Path(split_dir))
    sessions = []
    for cut in part.cuts:
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        sessions.append(ort.InferenceSession(str(cut.suffix), opts, ["CPUExecutionProvider"]))
    print(psutil.Process().memory_info().rss)


def breakdown_child(split_dir: str) -> None:
    """(In a child process) RSS after each step of a cloud daemon's model loading, as JSON:
    runtime imported, weights read, first suffix session built, every suffix session built,
    every suffix run once (activations)."""
    import numpy as np

    from common.partition import Partition
    from common.partition.runtime import SplitModel

    process = psutil.Process()
    steps = {"imported": process.memory_info().rss}
    model = SplitModel(Partition.load(Path(split_dir)), lazy=True)
    steps["weights read"] = process.memory_info().rss
    specs = [model.cut_tensor_specs(k) for k in range(model.num_cuts)]

    def run_suffix(k: int) -> None:
        model.run_suffix(k, {s.name: np.zeros(s.shape, dtype=s.dtype) for s in specs[k]})

    model._suffix_session(0)
    steps["first session built"] = process.memory_info().rss
    for k in range(1, model.num_cuts):
        model._suffix_session(k)
    steps["other sessions built"] = process.memory_info().rss
    for k in range(model.num_cuts):
        run_suffix(k)
    steps["every suffix run once"] = process.memory_info().rss
    print(json.dumps(steps))


def measure_breakdown(split_dir: Path) -> dict[str, int]:
    done = subprocess.run(
        [sys.executable, __file__, "--breakdown-child", str(split_dir)],
        capture_output=True,
        text=True,
        check=True,
    )
    steps: dict[str, int] = json.loads(done.stdout.strip().splitlines()[-1])
    return steps


def measure_naive(split_dir: Path) -> int:
    done = subprocess.run(
        [sys.executable, __file__, "--naive-child", str(split_dir)],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(done.stdout.strip().splitlines()[-1])


def median_rss(
    repeat: int, workdir: Path, model: str, shape: list[int] | None, names: list[str] | None
) -> int:
    """The median over `repeat` daemons (malloc's high-water marks vary from run to run)."""
    return int(
        statistics.median(
            measure_daemon(workdir / f"run{i}", model, shape, names) for i in range(repeat)
        )
    )


def run(naive: bool, breakdown: bool, repeat: int, workdir: Path) -> dict[str, Any]:
    rows: list[Row] = []
    base_model = str(weightless_model(workdir / "weightless.onnx"))
    weights, _, cuts = prepare(base_model, None, None)
    base_rss = median_rss(repeat, workdir / "base", base_model, None, None)
    baseline = Row("weightless", cuts, weights, base_rss)
    models: list[tuple[str, str, list[int] | None]] = [
        ("zoo:resnet 3x240x320", "zoo:resnet", RESNET_SHAPE),
        ("dense 15x1024x1024", str(dense_model(workdir / "dense.onnx")), None),
    ]  # fmt: skip
    for label, model, shape in models:
        for count in CUT_COUNTS:
            names = cut_names(model, shape, count)
            weights, split_dir, cuts = prepare(model, shape, names)
            run_dir = workdir / f"{label.split()[0].replace(':', '-')}-{count}"
            rss = median_rss(repeat, run_dir, model, shape, names)
            row = Row(label, cuts, weights, rss)
            if naive and count == TARGET_CUTS:
                row.naive_rss_bytes = measure_naive(split_dir)
            if breakdown and count == TARGET_CUTS:
                row.breakdown = measure_breakdown(split_dir)
            rows.append(row)
    return {"repeat": repeat, "baseline": asdict(baseline), "rows": [asdict(r) for r in rows]}


def _mb(n: float) -> str:
    return f"{n / MiB:.1f}"


def print_table(result: dict[str, Any]) -> None:
    base = result["baseline"]
    print(
        f"Runtime baseline (weightless model, {base['cuts']} cuts): {_mb(base['rss_bytes'])} MiB; "
        f"every RSS is the median of {result['repeat']} daemons"
    )
    print()
    print(
        "| model | cuts | weights MiB | RSS MiB | growth from 2 cuts MiB | RSS - baseline MiB "
        "| (RSS - baseline) / weights | bound: baseline + 1.5 x weights MiB | within "
        "| naive 16 sessions RSS MiB |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |")
    first: dict[str, int] = {}
    for row in result["rows"]:
        first.setdefault(row["model"], row["rss_bytes"])
        growth = row["rss_bytes"] - first[row["model"]]
        extra = row["rss_bytes"] - base["rss_bytes"]
        bound = base["rss_bytes"] + TARGET_RATIO * row["weight_bytes"]
        within = row["rss_bytes"] <= bound
        naive = row["naive_rss_bytes"]
        print(
            f"| {row['model']} | {row['cuts']} | {_mb(row['weight_bytes'])} | "
            f"{_mb(row['rss_bytes'])} | {_mb(growth)} | {_mb(extra)} | "
            f"{extra / row['weight_bytes']:.2f} | "
            f"{_mb(bound)} | {'yes' if within else 'NO'} | "
            f"{_mb(naive) if naive is not None else '-'} |"
        )
    steps = [(row["model"], row["breakdown"]) for row in result["rows"] if row["breakdown"]]
    if steps:
        print()
        print(f"Where a {TARGET_CUTS}-cut model's memory goes (one process, MiB added per step):")
        print()
        names = list(steps[0][1])
        print("| model | " + " | ".join(names[1:]) + " |")
        print("| --- |" + " ---: |" * (len(names) - 1))
        for model, step in steps:
            values = list(step.values())
            deltas = [_mb(b - a) for a, b in itertools.pairwise(values)]
            print(f"| {model} | " + " | ".join(deltas) + " |")


ROBOT_MODEL = "zoo:stereo"
ROBOT_SOURCE = "stereo:world"
ROBOT_RESOLUTIONS = "320x240,640x480"
ROBOT_ROUNDS = 3
NAV_FLEET = Path("nav")
"""`--robot` without a file: the navigation benchmark's fleet."""
RSS_SAMPLE_S = 0.01
VARIANTS = ("before", "after")
"""`before`: the robot as it was (every session, the segments' too; the startup runs' freed
memory left in the heap); `after`: as `elasticfog robot` starts now (`open_split_model`, then
`common.heap.trim_heap` once the profile is measured)."""


def nav_fleet(directory: Path, size: tuple[int, int]) -> Path:
    """The navigation benchmark's fleet at `size` (WxH): zoo:stereo split with segments, the
    robot on `stereo:world` frames with one onnxruntime thread (`experiments.nav`)."""
    return write_local_fleet(
        directory,
        model=ROBOT_MODEL,
        changes={
            "input_shape": [3, size[1], size[0]],
            "cuts": {"segments": True},
            "machines": {"robot-1": {"source": ROBOT_SOURCE, "threads": 1}},
            "fidelity": {"calibration_frames": 1},
        },
    )


class RssWatch:
    """The process's RSS now, and its peak since the last mark (sampled by a thread)."""

    def __init__(self) -> None:
        import threading

        self._process = psutil.Process()
        self._lock = threading.Lock()  # a sample must not land after a mark's reset
        self._peak = self._process.memory_info().rss
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="rss-watch", daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(RSS_SAMPLE_S):
            with self._lock:
                self._peak = max(self._peak, self._process.memory_info().rss)

    def mark(self) -> tuple[float, float]:
        """(RSS now, peak since the last mark), MiB; the peak starts again from now."""
        import gc

        gc.collect()
        with self._lock:
            now = self._process.memory_info().rss
            peak, self._peak = max(self._peak, now), now
        return round(now / MiB, 1), round(peak / MiB, 1)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def robot_breakdown(
    config: Path, robot_id: str | None, rounds: int, variant: str
) -> dict[str, Any]:
    """(In a child process) the robot daemon's start-up steps as it takes them, then `rounds`
    rounds of frames, each running every action the robot may take on a frame of its source
    (the whole model; every cut's prefix, then its suffix as a fallback does): per step the RSS
    after it and the peak during it (MiB), and each action's median time (ms)."""
    import resource

    watch = RssWatch()
    steps: dict[str, dict[str, float]] = {}

    def mark(step: str) -> None:
        rss, peak = watch.mark()
        steps[step] = {"rss_mib": rss, "peak_mib": peak}

    mark("python and this script")
    from common.config import load_fleet
    from common.heap import trim_heap
    from common.keys import Role
    from robotd.daemon import RobotDaemon  # noqa: F401 - what the daemon imports
    from robotd.robot_model import RobotModel, open_split_model
    from robotd.robot_profile import warm_up

    mark("imports (robotd.daemon)")
    cfg = load_fleet(config)
    robot = robot_id or cfg.robot_ids[0]
    machine = cfg.machine(robot, role=Role.ROBOT)
    model = open_split_model(cfg, machine)
    if variant == "before":
        model.build_all()  # the segments' sessions, which the robot used to build too
    sessions = len(model.session_providers())
    mark(f"sessions built ({model.num_cuts} cuts)")
    robot_model = RobotModel(model, cfg.model)
    warm_up(model, robot_model.sample_feeds)
    mark("warm-up (every prefix and suffix run once)")
    robot_model.profile(
        cfg, source_spec=machine.source, seed=0, threads=machine.threads, policy_spec="robot"
    )
    mark("profile and codec calibration")
    if variant == "after":
        trim_heap()
    mark("freed heap returned (after only)")
    source = robot_model.open_source(machine.source, seed=0)
    mark(f"source {machine.source} opened")
    times: dict[str, list[float]] = {}
    cpu: dict[str, list[float]] = {}
    faults: dict[str, list[int]] = {}

    def frame(k: int | None) -> None:
        """One frame of the source: the whole model (k None), or cut k's prefix and suffix.
        Its wall time is at the mercy of a shared host; its CPU time and page faults are not."""
        feeds = robot_model.feeds(source.read())
        faulted = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        started, cpu_started = time.perf_counter(), time.process_time()
        if k is None:
            model.run_full(feeds)
        else:
            model.run_suffix(k, model.run_prefix(k, feeds), feeds)
        action = "whole model" if k is None else f"cut {k}: prefix + suffix"
        times.setdefault(action, []).append((time.perf_counter() - started) * 1e3)
        cpu.setdefault(action, []).append((time.process_time() - cpu_started) * 1e3)
        faulted = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faulted
        faults.setdefault(action, []).append(faulted)

    for _ in range(rounds):
        for k in [None, *range(model.num_cuts)]:
            frame(k)
    mark(f"{rounds} rounds of frames (steady state)")
    source.close()
    watch.close()
    return {
        "variant": variant,
        "input_shape": list(cfg.input_shape or []),
        "sessions": sessions,
        "steps": steps,
        "max_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "times_ms": {a: [round(x, 1) for x in t] for a, t in times.items()},
        "cpu_ms": {a: [round(x, 1) for x in t] for a, t in cpu.items()},
        "minor_faults": faults,
    }


def measure_robot(config: Path, robot_id: str | None, rounds: int, variant: str) -> dict[str, Any]:
    """`robot_breakdown` in a fresh interpreter (RSS is a process's own)."""
    command = [sys.executable, __file__, "--robot-child", str(config), "--variant", variant]
    command += ["--rounds", str(rounds)] + (["--robot-id", robot_id] if robot_id else [])
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{variant} robot at {config} exited {done.returncode}:\n{done.stderr}")
    result: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def run_robot(
    fleet: Path | None,
    resolutions: list[tuple[int, int]],
    robot_id: str | None,
    rounds: int,
    pairs: int,
    workdir: Path,
) -> list[dict[str, Any]]:
    """`pairs` times both variants, one after the other (before, after, before, ...: a shared
    host's load drifts), at each resolution (or for `fleet` only)."""
    fleets = [fleet] if fleet is not None else []
    for w, h in [] if fleet is not None else resolutions:
        fleets.append(nav_fleet(workdir / f"{w}x{h}", (w, h)))
    return [
        measure_robot(f, robot_id, rounds, v)
        for f in fleets
        for _ in range(pairs)
        for v in VARIANTS
    ]


def print_robot(results: list[dict[str, Any]]) -> None:
    """Per resolution: each step's median RSS over the runs of each variant, and each action's
    median time over all of a variant's frames."""
    shapes: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for r in results:
        runs = shapes.setdefault("x".join(map(str, r["input_shape"])), {})
        runs.setdefault(r["variant"], []).append(r)
    for shape, by in shapes.items():
        before, after = by["before"], by["after"]

        def med(runs: list[dict[str, Any]], step: str, key: str) -> float:
            return statistics.median(r["steps"][step][key] for r in runs)

        def peak(runs: list[dict[str, Any]]) -> float:
            return statistics.median(r["max_rss_mib"] for r in runs)

        print(
            f"### {shape}: {before[0]['sessions']} sessions before, {after[0]['sessions']} "
            f"after; process peak {peak(before):.0f} / {peak(after):.0f} MiB "
            f"(medians of {len(before)} / {len(after)} runs)"
        )
        print()
        print("| step | before: RSS MiB | peak during | after: RSS MiB | peak during |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for step in before[0]["steps"]:
            print(
                f"| {step} | {med(before, step, 'rss_mib'):.0f} "
                f"| {med(before, step, 'peak_mib'):.0f} | {med(after, step, 'rss_mib'):.0f} "
                f"| {med(after, step, 'peak_mib'):.0f} |"
            )
        print()
        print(
            "| action (median over frames) | before: wall ms | CPU ms | page faults "
            "| after: wall ms | CPU ms | page faults | CPU after / before |"
        )
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")

        def frames(runs: list[dict[str, Any]], key: str, action: str) -> float:
            return statistics.median(t for r in runs for t in r[key][action])

        for a in before[0]["times_ms"]:
            b_cpu, a_cpu = frames(before, "cpu_ms", a), frames(after, "cpu_ms", a)
            print(
                f"| {a} | {frames(before, 'times_ms', a):.0f} | {b_cpu:.0f} "
                f"| {frames(before, 'minor_faults', a):.0f} | {frames(after, 'times_ms', a):.0f} "
                f"| {a_cpu:.0f} | {frames(after, 'minor_faults', a):.0f} | {a_cpu / b_cpu:.2f} |"
            )
        print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--naive", action="store_true", help="also measure unshared sessions")
    parser.add_argument("--repeat", type=int, default=3, help="daemons per figure (median)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument(
        "--breakdown", action="store_true", help="also show where the memory goes, step by step"
    )
    parser.add_argument(
        "--robot",
        metavar="FLEET",
        nargs="?",
        type=Path,
        const=NAV_FLEET,
        help="the robot daemon's start-up steps and frames instead (default: the navigation "
        "benchmark's fleet at each of --resolutions)",
    )
    parser.add_argument("--robot-id", help="which robot of the fleet (default: the first)")
    parser.add_argument(
        "--resolutions", default=ROBOT_RESOLUTIONS, help="WxH,... of the navigation fleet"
    )
    parser.add_argument(
        "--rounds", type=int, default=ROBOT_ROUNDS, help="rounds of every robot action run"
    )
    parser.add_argument(
        "--pairs", type=int, default=1, help="robot runs of each variant, alternated"
    )
    parser.add_argument("--naive-child", metavar="SPLIT_DIR", help=argparse.SUPPRESS)
    parser.add_argument("--breakdown-child", metavar="SPLIT_DIR", help=argparse.SUPPRESS)
    parser.add_argument("--robot-child", metavar="FLEET", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--variant", choices=VARIANTS, default="after", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.naive_child:
        naive_child(args.naive_child)
        return
    if args.breakdown_child:
        breakdown_child(args.breakdown_child)
        return
    if args.robot_child:
        result = robot_breakdown(args.robot_child, args.robot_id, max(1, args.rounds), args.variant)
        print(json.dumps(result))
        return
    if args.robot is not None:
        from experiments.nav_rows import parse_resolutions

        fleet = None if args.robot == NAV_FLEET else args.robot
        with tempfile.TemporaryDirectory(prefix="memory-bench-") as tmp:
            results = run_robot(
                fleet,
                parse_resolutions(args.resolutions),
                args.robot_id,
                max(1, args.rounds),
                max(1, args.pairs),
                Path(tmp),
            )
        if args.json:
            print(json.dumps(results, indent=2))
        else:
            print_robot(results)
        return
    with tempfile.TemporaryDirectory(prefix="memory-bench-") as tmp:
        result = run(args.naive, args.breakdown, max(1, args.repeat), Path(tmp))
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print_table(result)


if __name__ == "__main__":
    main()
