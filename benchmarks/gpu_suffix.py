"""Suffix time per frame on the CPU vs the GPU, and what the batcher serves at 8 and 16 robots.

For each model (zoo:resnet18, zoo:mobilenet_v2 and a public torchvision architecture exported and
wrapped by `model prep`, `torchvision:NAME`), the cloud's part at one cut (default: the model's
input, so the whole model is the suffix) runs the way a deployment serves it (`SplitModel`,
shared weights, the cloud's session options) on each provider asked for:

- **suffix**: wall time per frame of one run at batch 1, 8 and 16 (median and p95 over the
  rounds; sizes interleaved round by round, so a neighbour's load falls on all alike); on a GPU
  provider with and without IO binding. Inputs are photographs (`common.photos`).
- **serving**: N robots (threads, one frame in flight each, the next sent when the reply is in)
  offer frames to the deployment's own queue (`cloudd.batch_queue.FairQueue`, the policy of
  `batching`), served by `--workers` workers: batch 1 (batching off) vs the batcher (batching
  on, preferred sizes 8 and 16, buckets and warm-up with `gpu_serving` on a GPU), for N = 8
  and 16. Per cell frames/s, p50/p95 latency (offer to result), mean batch; per N the batcher's
  gain in frames/s over batch 1 and whether its p95 is no worse than batch 1's.

A provider this host cannot give (CUDA in a CPU build of onnxruntime, TensorRT without its
libraries) is a row with `skipped` and the reason `common.providers` names, never a CPU run
under the GPU's name. JSON on stdout (and `--out FILE`); progress on stderr.

    python benchmarks/gpu_suffix.py [--models zoo:resnet18,zoo:mobilenet_v2,torchvision:resnet50]
        [--providers cpu,cuda,tensorrt] [--serving-providers cpu,cuda,tensorrt] [--cut input|mid]
        [--rounds 20] [--robots 8,16] [--duration-s 5] [--workers 2] [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cloudd.batch_queue import BatchPolicy, FairQueue, Pending
from common.config import BatchingConfig
from common.defaults import ZOO_PREFIX
from common.image_input import InputAdapter
from common.models import cache_dir, resolve_model
from common.partition import load_partition
from common.partition.runtime import SplitModel
from common.photos import still_views
from common.providers import (
    ProviderSpec,
    check_session,
    ort_providers,
    parse_provider,
    prepare,
)
from common.zoo import parse_shape

DEFAULT_MODELS = ("zoo:resnet18", "zoo:mobilenet_v2", "torchvision:resnet50")
TORCHVISION_PREFIX = "torchvision:"
ZOO_INPUT_SHAPE = (3, 224, 224)
SUFFIX_SIZES = (1, 8, 16)
DEFAULT_ROUNDS = 20
DEFAULT_ROBOTS = (8, 16)
DEFAULT_DURATION_S = 5.0
DEFAULT_WORKERS = 2
WARMUP_S = 1.0
"""Serving: frames in the first second of a cell are not counted (queues and clocks settle)."""
BATCHER_SIZES = (8, 16)
BATCHER_DELAY_S = 0.005
"""The batcher's policy: preferred sizes and longest wait (the deployment's defaults, at 16)."""
REQUEST_BUDGET_S = 30.0
"""A frame's deadline in the queue: long enough that none expires (throughput is measured)."""
MAX_FRAMES_PER_ROBOT = 100_000
"""Bound on one robot's frames in a cell, whatever the duration."""
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
TORCHVISION_SIDE_PX = 224
QUICK = {"rounds": 3, "duration_s": 1.5, "robots": (8,)}


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# -- models --------------------------------------------------------------------------------------
def torchvision_model(name: str, work: Path) -> Path:
    """torchvision's `name` (seeded, no weights: the time does not depend on them) exported to
    ONNX as benchmarks/public_archs.py does, then wrapped by `model prep` to take the camera
    image (uint8 N×H×W×3, ImageNet mean and std in the graph); cached in `work`."""
    from common.prep import prep_model

    out = work / f"{name}.prep.onnx"
    if out.exists():
        return out
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from public_archs import export

    work.mkdir(parents=True, exist_ok=True)
    raw = work / f"{name}.onnx"
    export(name, raw)
    prep_model(
        raw,
        out,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
        input_size=(TORCHVISION_SIDE_PX, TORCHVISION_SIDE_PX),
    )
    return out


def open_partition(
    spec: str, cut: str, work: Path, zoo_shape: tuple[int, ...] = ZOO_INPUT_SHAPE
) -> Any:
    """The model split at one cut: its input (the whole model is the suffix; one cut to verify)
    or the middle one of every cut found."""
    shape: tuple[int, ...] | None = None
    if spec.startswith(TORCHVISION_PREFIX):
        source = str(torchvision_model(spec[len(TORCHVISION_PREFIX) :], work))
    elif spec.startswith(ZOO_PREFIX):
        source, shape = spec, zoo_shape
    else:  # an ONNX file that takes the camera image (`model prep`)
        source = spec
    if cut == "input":
        return load_partition(source, cuts=input_names(source, shape), input_shape=shape)
    return load_partition(source, input_shape=shape)


def input_names(source: str, shape: tuple[int, ...] | None) -> list[str]:
    """The model's inputs (graph inputs that are not initializers): the cut at the input."""
    import onnx

    path = resolve_model(source, shape).path
    graph = onnx.load(str(path), load_external_data=False).graph
    weights = {t.name for t in graph.initializer}
    return [i.name for i in graph.input if i.name not in weights]


def cut_index(partition: Any, cut: str) -> int:
    return 0 if cut == "input" else len(partition.cuts) // 2


# -- suffix time ---------------------------------------------------------------------------------
@dataclass
class Frames:
    """Each robot's frame at the cut: the tensors of a photograph, one per robot."""

    items: list[dict[str, np.ndarray]]


def frames_for(model: SplitModel, k: int, count: int) -> Frames:
    spec = model.input_specs()[0]
    adapter = InputAdapter(spec)
    views = still_views(count)
    return Frames([model.run_prefix(k, {spec.name: adapter(v)}) for v in views])


def open_model(partition: Any, spec: ProviderSpec, *, io_binding: bool, buckets: Any) -> SplitModel:
    providers = [spec] if spec.ort_name == "CPUExecutionProvider" else [spec, parse_provider("cpu")]
    return SplitModel(
        partition,
        providers=ort_providers(providers),
        lazy=True,
        io_binding=io_binding,
        buckets=buckets,
    )


def provider_problem(model: SplitModel, k: int, spec: ProviderSpec) -> str | None:
    """Why the suffix session did not get `spec` (the daemon's own check), or None."""
    check = check_session(model.suffix_providers(k), [spec])
    return "; ".join(reason for _, reason in check.missing) or None


def suffix_rows(
    partition: Any, k: int, spec: ProviderSpec, frames: Frames, rounds: int
) -> list[dict[str, Any]]:
    """Per-frame wall time at each batch size, with and without IO binding on a GPU."""
    rows: list[dict[str, Any]] = []
    bindings = (False, True) if spec.gpu else (False,)
    for io_binding in bindings:
        model = open_model(partition, spec, io_binding=io_binding, buckets=None)
        problem = provider_problem(model, k, spec)
        if problem is not None:
            return [{"provider": spec.label, "skipped": problem}]
        reason = model.enable_batching(k)
        sizes = SUFFIX_SIZES if reason is None else (1,)
        times: dict[int, list[float]] = {n: [] for n in sizes}
        for n in sizes:  # first runs: cuDNN algorithm search, engine builds
            model.run_suffix_batch(k, frames.items[:n])
        for _ in range(rounds):
            for n in sizes:
                t0 = time.perf_counter()
                model.run_suffix_batch(k, frames.items[:n])
                times[n].append((time.perf_counter() - t0) / n)
        for n in sizes:
            rows.append(
                {
                    "provider": spec.label,
                    "io_binding": io_binding,
                    "batch": n,
                    "ms_per_frame_median": 1000 * statistics.median(times[n]),
                    "ms_per_frame_p95": ms(percentile(times[n], 95)),
                    "rounds": rounds,
                    **({"unbatched": reason} if reason is not None else {}),
                }
            )
        model.close()
    return rows


def percentile(values: list[float], q: float) -> float | None:
    """None for no values (a cell where no frame finished in time): JSON has no NaN."""
    return float(np.percentile(np.asarray(values), q)) if values else None


def ms(seconds: float | None) -> float | None:
    return None if seconds is None else 1000 * seconds


# -- serving -------------------------------------------------------------------------------------
@dataclass(eq=False)
class Job:
    """One robot's frame in the queue, and where its worker puts the result."""

    tensors: dict[str, np.ndarray]
    done: threading.Event = field(default_factory=threading.Event)
    error: str | None = None


@dataclass
class Cell:
    latencies_s: list[float] = field(default_factory=list)
    batches: list[int] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    busy: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


def serve(
    model: SplitModel,
    k: int,
    frames: Frames,
    *,
    robots: int,
    policy: BatchPolicy,
    workers: int,
    duration_s: float,
) -> dict[str, Any]:
    """`robots` closed-loop robots against `workers` workers on one FairQueue; the cell's
    figures over `duration_s` after WARMUP_S."""
    queue: FairQueue[Job] = FairQueue(
        policy,
        slots=robots * policy.max_in_flight_per_robot + workers * policy.max_batch,
        batchable=model.batched,
    )
    cell = Cell()
    started = time.monotonic()
    counted_from = started + WARMUP_S
    end = counted_from + duration_s

    def worker() -> None:
        while True:
            batch = queue.get(timeout_s=0.1)
            if batch is None:
                if queue.closed:
                    return
                continue
            jobs = [item.payload for item in batch.items]
            try:
                if jobs:
                    model.run_suffix_batch(k, [job.tensors for job in jobs])
            except Exception as exc:  # a failed run is a result of the cell, named
                for job in jobs:
                    job.error = str(exc)
            queue.done(batch)
            if batch.items and time.monotonic() >= counted_from:
                with cell.lock:
                    cell.batches.append(len(batch.items))
            for item in (*batch.items, *batch.expired):
                item.payload.done.set()

    def robot(index: int) -> None:
        name = f"robot-{index}"
        tensors = frames.items[index % len(frames.items)]
        for _ in range(MAX_FRAMES_PER_ROBOT):
            now = time.monotonic()
            if now >= end:
                return
            job = Job(tensors)
            refusal = queue.offer(Pending(name, k, now, now + REQUEST_BUDGET_S, job))
            if refusal is not None:
                with cell.lock:
                    cell.busy += 1
                job.done.wait(0.001)  # nothing to wait for: a short pause before the next try
                continue
            job.done.wait(REQUEST_BUDGET_S)
            finished = time.monotonic()
            if now >= counted_from and finished <= end:
                with cell.lock:
                    if job.error is not None:
                        cell.errors.append(job.error)
                    else:
                        cell.latencies_s.append(finished - now)

    threads = [threading.Thread(target=worker, daemon=True) for _ in range(workers)]
    threads += [threading.Thread(target=robot, args=(i,), daemon=True) for i in range(robots)]
    for t in threads:
        t.start()
    for t in threads[workers:]:
        t.join(duration_s + WARMUP_S + REQUEST_BUDGET_S)
    queue.close()
    for t in threads[:workers]:
        t.join(REQUEST_BUDGET_S)
    lat = cell.latencies_s
    return {
        "frames": len(lat),
        "fps": len(lat) / duration_s,
        "p50_ms": ms(percentile(lat, 50)),
        "p95_ms": ms(percentile(lat, 95)),
        "mean_batch": statistics.fmean(cell.batches) if cell.batches else 0.0,
        "largest_batch": max(cell.batches, default=0),
        "busy": cell.busy,
        "errors": sorted(set(cell.errors))[:3],
    }


def serving_rows(
    partition: Any,
    k: int,
    spec: ProviderSpec,
    frames: Frames,
    *,
    robot_counts: tuple[int, ...],
    workers: int,
    duration_s: float,
) -> list[dict[str, Any]]:
    """Batch 1 vs the batcher at each robot count, on one provider."""
    gpu = spec.gpu
    one = open_model(partition, spec, io_binding=gpu, buckets=None)
    problem = provider_problem(one, k, spec)
    if problem is not None:
        return [{"provider": spec.label, "skipped": problem}]
    batched = open_model(partition, spec, io_binding=gpu, buckets=None)
    reason = batched.enable_batching(k)
    if reason is not None:
        return [{"provider": spec.label, "skipped": f"cut {k} takes no batch: {reason}"}]
    if gpu:  # gpu_serving: buckets and every bucket warmed, as the daemon does
        buckets = BatchingConfig(enabled=True, preferred_batch_sizes=list(BATCHER_SIZES))
        batched.buckets = buckets.bucket_sizes
        batched.warm_batches(k, batched.buckets)
    one.run_suffix(k, frames.items[0])
    rows = []
    for robots in robot_counts:
        cells = {}
        for mode, model, policy in (
            ("batch1", one, BatchPolicy((1,), 0.0, 1)),
            ("batcher", batched, BatchPolicy(BATCHER_SIZES, BATCHER_DELAY_S, 1)),
        ):
            log(f"    serving {spec.label}: {robots} robots, {mode}")
            cells[mode] = serve(
                model,
                k,
                frames,
                robots=robots,
                policy=policy,
                workers=workers,
                duration_s=duration_s,
            )
            rows.append({"provider": spec.label, "robots": robots, "mode": mode, **cells[mode]})
    one.close()
    batched.close()
    return rows


# -- the run -------------------------------------------------------------------------------------
def host_facts() -> dict[str, Any]:
    import onnxruntime as ort

    try:
        from onnxruntime.capi import build_and_package_info as info

        package = str(info.package_name)
        cuda = str(getattr(info, "cuda_version", "") or "")
    except ImportError:
        package, cuda = "onnxruntime", ""
    facts: dict[str, Any] = {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": sys.version.split()[0],
        "onnxruntime": f"{package} {ort.__version__}",
        "onnxruntime_cuda": cuda or None,
        "available_providers": ort.get_available_providers(),
        "gpu": None,
    }
    smi = shutil.which("nvidia-smi")
    if smi is not None:
        done = subprocess.run(
            [smi, "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        facts["gpu"] = done.stdout.strip() or done.stderr.strip() or None
    return facts


def bench_model(spec: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    started = time.perf_counter()
    partition = open_partition(spec, args.cut, work, args.input_shape)
    k = cut_index(partition, args.cut)
    cpu_model = SplitModel(partition, lazy=True)
    frames = frames_for(cpu_model, k, max(max(SUFFIX_SIZES), max(args.robots)))
    cpu_model.close()
    row: dict[str, Any] = {
        "model": spec,
        "cut": k,
        "cut_tensors": list(partition.cuts[k].tensors),
        "input": [list(s.shape) for s in (partition.specs[n] for n in partition.inputs)],
        "prepare_s": round(time.perf_counter() - started, 1),
        "suffix": [],
        "serving": [],
    }
    for provider in args.providers:
        log(f"  suffix on {provider.label}")
        row["suffix"] += suffix_rows(partition, k, provider, frames, args.rounds)
    for provider in args.serving_providers:
        row["serving"] += serving_rows(
            partition,
            k,
            provider,
            frames,
            robot_counts=args.robots,
            workers=args.workers,
            duration_s=args.duration_s,
        )
    row["summary"] = summary(row["suffix"], row["serving"])
    return row


def summary(suffix: list[dict[str, Any]], serving: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures the question asks for: per provider the suffix time per frame at batch 1
    (the better of with and without IO binding) and its speed-up over the CPU's; per provider
    and robot count the batcher's frames/s over batch 1's and whether its p95 is no worse."""
    batch1: dict[str, float] = {}
    for r in suffix:
        if r.get("batch") == 1:
            label = r["provider"]
            batch1[label] = min(batch1.get(label, float("inf")), r["ms_per_frame_median"])
    cpu = batch1.get("cpu")
    out: dict[str, Any] = {
        "suffix_ms_batch1": batch1,
        "speedup_vs_cpu_batch1": {p: cpu / ms for p, ms in batch1.items()} if cpu else {},
        "batching": [],
    }
    cells = {(r["provider"], r["robots"], r["mode"]): r for r in serving if "mode" in r}
    for (provider, robots, mode), base in cells.items():
        best = cells.get((provider, robots, "batcher"))
        if mode != "batch1" or best is None:
            continue
        out["batching"].append(
            {
                "provider": provider,
                "robots": robots,
                "fps_batch1": base["fps"],
                "fps_batcher": best["fps"],
                "fps_gain": best["fps"] / base["fps"] if base["fps"] else None,
                "p95_ms_batch1": base["p95_ms"],
                "p95_ms_batcher": best["p95_ms"],
                "p95_no_worse": (
                    None
                    if best["p95_ms"] is None or base["p95_ms"] is None
                    else best["p95_ms"] <= base["p95_ms"]
                ),
            }
        )
    return out


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default=",".join(DEFAULT_MODELS))
    parser.add_argument("--providers", default="cpu,cuda,tensorrt")
    parser.add_argument(
        "--serving-providers",
        default=None,
        help="providers of the serving cells (default: --providers)",
    )
    parser.add_argument("--cut", choices=("input", "mid"), default="input")
    parser.add_argument(
        "--input-shape", default="x".join(map(str, ZOO_INPUT_SHAPE)), help="zoo models: CxHxW"
    )
    parser.add_argument("--rounds", type=int, default=DEFAULT_ROUNDS)
    parser.add_argument("--robots", default=",".join(map(str, DEFAULT_ROBOTS)))
    parser.add_argument("--duration-s", type=float, default=DEFAULT_DURATION_S)
    parser.add_argument("--workers", type=int, default=DEFAULT_WORKERS)
    parser.add_argument("--work", type=Path, default=None, help="folder for exported models")
    parser.add_argument("--quick", action="store_true", help="3 rounds, 1.5 s cells, 8 robots")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    try:
        args.providers = [parse_provider(p.strip()) for p in args.providers.split(",") if p.strip()]
        serving = args.serving_providers
        args.serving_providers = (
            args.providers
            if serving is None
            else [parse_provider(p.strip()) for p in serving.split(",") if p.strip()]
        )
    except ValueError as exc:
        parser.error(str(exc))
    args.models = [m.strip() for m in args.models.split(",") if m.strip()]
    args.input_shape = parse_shape(args.input_shape)
    args.robots = tuple(int(n) for n in args.robots.split(","))
    if args.quick:
        args.rounds, args.duration_s = QUICK["rounds"], QUICK["duration_s"]
        args.robots = QUICK["robots"]
    return args


def rounded(value: Any) -> Any:
    """Floats to 4 significant digits, for a readable JSON."""
    if isinstance(value, float):
        return float(f"{value:.4g}")
    if isinstance(value, dict):
        return {k: rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [rounded(v) for v in value]
    return value


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    # onnxruntime's warning when it drops a provider: each such row says why, by the check.
    warnings.filterwarnings("ignore", message="Specified provider", category=UserWarning)
    prepare([*args.providers, *args.serving_providers])
    work = args.work or cache_dir() / "gpu-bench-models"
    result: dict[str, Any] = {
        "host": host_facts(),
        "settings": {
            "models": args.models,
            "providers": [p.label for p in args.providers],
            "serving_providers": [p.label for p in args.serving_providers],
            "cut": args.cut,
            "rounds": args.rounds,
            "suffix_batches": list(SUFFIX_SIZES),
            "robots": list(args.robots),
            "duration_s": args.duration_s,
            "workers": args.workers,
            "batcher": {
                "preferred_sizes": list(BATCHER_SIZES),
                "max_queue_delay_s": BATCHER_DELAY_S,
            },
        },
        "models": [],
    }
    for n, spec in enumerate(args.models, 1):
        log(f"[{n}/{len(args.models)}] {spec}")
        try:
            result["models"].append(bench_model(spec, args, work))
        except Exception as exc:  # one model failing is a result too; the others still run
            result["models"].append({"model": spec, "error": " ".join(str(exc).split())[:500]})
            log(f"  FAILED: {exc}")
        if args.out is not None:  # after each model: a run cut short keeps what it measured
            args.out.write_text(
                json.dumps(rounded(result), indent=2, allow_nan=False) + "\n", encoding="utf-8"
            )
    print(json.dumps(rounded(result), indent=2, allow_nan=False))
    return 0 if all("error" not in m for m in result["models"]) else 1


if __name__ == "__main__":
    sys.exit(main())
