"""Many robots on this host (`elasticfog bench scale`): what the cloud serves as robots are added.

Loopback, no root. For each number of deployments and each batching mode, a fleet is started as
a user would start it (`elasticfog registry` and one `elasticfog cloud` per deployment, real
subprocesses), and for each number of robots a load generator (`experiments.load_generator`, as
Triton's perf_analyzer drives a server) emulates the robots: each declares its liveliness token,
is routed by the registry, and sends real inference requests over Zenoh to its anycast service
key at the robot frame rate, one frame at a time, with the fleet's deadline. The robots are
emulated, not robot daemons: they run no prefix, no policy and publish no telemetry, and a frame
the cloud does not serve (busy, error, timeout) is counted, not finished locally.

Routing: the fleet's initial_policy puts every robot in service on edge-1 (what a fleet file
written for one deployment says), and the registry places each robot by load when its token
appears: on the deployment with the most headroom (`registry.scheduler`, placement by load), the
initial policy breaking ties; with no telemetry nothing moves a robot afterwards. Each cell's
`timeline` counts the frames each deployment served in every TIMELINE_BIN_S from the load
generator's start (warm-up included), and `first_served_s` when each deployment served its first
frame: placement by load shows as every deployment serving within the first seconds.

Per cell (robots x deployments x batching), over a window after a warm-up: frames per second
served by the cloud, the served frames' latency (median, p95; send to reply, as the robot sees
the cloud part of a frame), the rates of busy and timeout replies, each deployment's share of
the served frames, and the cloud daemons' CPU seconds (user + system, read from /proc through
psutil) per served frame, hence frames per second per core. Each configuration's daemons are
started once and serve its robot counts in turn.

With `pin_cloud` (`--pin-cloud`) the cloud daemons run on CPUs of their own and the registry and
the load generators on the others (`pinned`), so that the robots' load does not take the
deployments' CPUs. One robot beside a hog on one deployment (`--fairness`) is in `fairness`.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

from common.config import FleetConfig, load_fleet
from common.errors import UserError
from deploy.cpu_pinning import CpuSplit, off_set_threads, pin_process, split_for_cloud, usable_cpus
from deploy.local_fleet import LocalFleet, write_local_fleet
from deploy.procs import DaemonProc
from experiments.load_generator import ARRIVALS, FrameOutcome, FrameRecord, LoadGenerator, summarize

from . import scale_defaults as defaults
from .cpu_share import CpuMeter
from .options import bench_workdir, model_path, option_dir
from .report import fmt, md_table, save_plot, use_agg

LOAD_KIND = "load generator (emulated robots; real Zenoh requests to real cloud daemons)"
ROUTED_TIMEOUT_S = 60.0
"""How long every robot of a cell may take to be routed and have a first frame served."""
TIMELINE_BIN_S = 0.5
"""Width of a bin of a cell's per-deployment `timeline`, seconds."""
SPREAD_WITHIN_S = 2.0
"""The bar of placement by load: every deployment serves within this long of the start."""
MUST_SHOW_ROBOTS = 8
MUST_SHOW_RATIO = 1.5
"""The issue's bar: frames/s per core with batching >= 1.5x without, at 8 robots, 1 deployment."""


@dataclass
class ScaleOptions:
    """What `elasticfog bench scale` runs (the defaults are the issue's setting)."""

    robots: Sequence[int] = defaults.ROBOTS
    deployments: Sequence[int] = defaults.DEPLOYMENTS
    batching: Sequence[bool] = (False, True)
    model: str = defaults.MODEL
    input_shape: tuple[int, ...] = defaults.INPUT_SHAPE
    fps: float = defaults.FPS
    warmup_s: float = defaults.WARMUP_S
    duration_s: float = defaults.DURATION_S
    cut: int = defaults.CUT
    codec: str = defaults.CODEC
    deadline_s: float = defaults.DEADLINE_S
    bound_s: float = defaults.BOUND_S
    """The fleet's latency bound (p95 of the frames' latency), seconds."""
    workers: int = defaults.WORKERS
    threads: int = defaults.THREADS
    queue: int = defaults.QUEUE
    max_queue_delay_ms: float = defaults.MAX_QUEUE_DELAY_MS
    batch_sizes: Sequence[int] = defaults.BATCH_SIZES
    max_in_flight_per_robot: int = defaults.MAX_IN_FLIGHT_PER_ROBOT
    pin_cloud: bool = False
    """Pin the cloud daemons to CPUs of their own, the rest of the bench to the others."""
    heavy_low_priority: bool = True
    """The deployments' `batching.heavy_robots_low_priority` (the fairness bench runs both)."""
    arrivals: str = "periodic"
    """How each robot's frames are spaced: "periodic" (a camera) or "poisson" (same mean rate)."""
    workdir: Path | None = None
    log: Callable[[str], None] = field(default=lambda message: None)

    def check(self) -> None:
        if not self.robots or min(self.robots) < 1:
            raise UserError("--robots: expected positive counts, e.g. 1,2,4,8")
        if not self.deployments or min(self.deployments) < 1:
            raise UserError("--deployments: expected positive counts, e.g. 1,2")
        for name, value in (
            ("--fps", self.fps),
            ("--duration-s", self.duration_s),
            ("--deadline-s", self.deadline_s),
            ("--bound-s", self.bound_s),
        ):
            if not value > 0:
                raise UserError(f"{name} {value:g}: expected a positive number")
        if self.warmup_s < 0:
            raise UserError(f"--warmup-s {self.warmup_s:g}: expected >= 0")
        if self.workers < 1 or self.queue < 0 or self.threads < 0:
            raise UserError("--workers >= 1, --queue >= 0 and --threads >= 0 are expected")
        if self.arrivals not in ARRIVALS:
            raise UserError(f"--arrivals {self.arrivals!r}: expected one of {', '.join(ARRIVALS)}")
        if self.pin_cloud:
            self.cpu_split(max(self.deployments))  # refused here, before any daemon starts
        # Paths are the working directory's, checked before anything starts.
        self.model = model_path(self.model)
        if self.workdir is not None:
            self.workdir = option_dir(self.workdir, "--workdir")

    def cpu_split(self, deployments: int) -> CpuSplit:
        """With `pin_cloud`: a CPU per worker of the deployments, at most all CPUs but one."""
        return split_for_cloud(usable_cpus(), deployments * self.workers)


def parse_counts(text: str, what: str) -> list[int]:
    """'1,2,4' -> [1, 2, 4]; a UserError naming `what` for anything else."""
    counts = []
    for part in (p.strip() for p in text.split(",")):
        if not part.isdigit() or int(part) < 1:
            raise UserError(f"{what}: {part!r} is not a positive whole number (e.g. 1,2,4)")
        counts.append(int(part))
    return list(dict.fromkeys(counts))


def parse_batching(text: str) -> list[bool]:
    """--batching on|off|both -> the modes to run (off first: the baseline)."""
    modes = {"on": [True], "off": [False], "both": [False, True]}
    if text not in modes:
        raise UserError(f"--batching {text!r}: expected on, off or both")
    return modes[text]


def deployment_ids(deployments: int) -> list[str]:
    return [f"edge-{i}" for i in range(1, deployments + 1)]


def robot_ids(robots: int) -> list[str]:
    return [f"robot-{i}" for i in range(1, robots + 1)]


def fleet_changes(options: ScaleOptions, deployments: int, batching: bool) -> dict[str, Any]:
    """What the bench changes in `elasticfog init`'s fleet: the model, the deadline and bound,
    the deployments (workers, batching) and the robots, robot i served by deployment i mod D."""
    clouds = deployment_ids(deployments)
    robots = robot_ids(max(options.robots))
    section = {
        "enabled": batching,
        "max_queue_delay_ms": options.max_queue_delay_ms,
        "preferred_batch_sizes": list(options.batch_sizes),
        "max_in_flight_per_robot": options.max_in_flight_per_robot,
        "heavy_robots_low_priority": options.heavy_low_priority,
    }
    machines: dict[str, Any] = {
        cloud: {
            "role": "cloud",
            "listen": ["tcp/127.0.0.1:0"],
            "workers": options.workers,
            "threads": options.threads,
            "queue": options.queue,
            "batching": section,
        }
        for cloud in clouds
    }
    machines.update({r: {"role": "robot", "listen": ["tcp/127.0.0.1:0"]} for r in robots})
    # Every robot in service on the first deployment: spreading them is the registry's job.
    policy: dict[str, Any] = {r: "robot" for r in robots}
    for i, cloud in enumerate(clouds):
        policy[cloud] = "service" if i == 0 else "standby"
    return {
        "input_shape": list(options.input_shape),
        "deadline_s": options.deadline_s,
        "latency_bound": {"stat": "p95", "seconds": options.bound_s},
        "policy": {"kind": "cloud"},
        "machines": machines,
        "initial_policy": policy,
    }


@dataclass
class RunningFleet:
    """A started fleet: its config, registry and cloud daemons, and the CPUs they are pinned to
    (None: not pinned)."""

    cfg: FleetConfig
    registry: DaemonProc
    clouds: list[DaemonProc]
    cpus: CpuSplit | None = None

    def threads_off_cpus(self) -> int:
        """Cloud daemon threads not on the cloud's CPUs now (0 unless pinning failed)."""
        if self.cpus is None:
            return 0
        return sum(len(off_set_threads(c.pid, self.cpus.cloud)) for c in self.clouds)


@contextlib.contextmanager
def running_fleet(
    options: ScaleOptions, workdir: Path, deployments: int, batching: bool, label: str = ""
) -> Iterator[RunningFleet]:
    """A registry and `deployments` cloud daemons of a fresh fleet, ready, stopped on exit;
    pinned with `options.pin_cloud` (`pinned`)."""
    label = label or f"d{deployments}-{'on' if batching else 'off'}"
    directory = workdir / label
    path = write_local_fleet(
        directory,
        fleet=f"scale-{uuid.uuid4().hex[:8]}",
        model=options.model,
        changes=fleet_changes(options, deployments, batching),
    )
    cfg = load_fleet(path)
    with LocalFleet(path, directory, startup_timeout_s=ROUTED_TIMEOUT_S) as lf:
        options.log(f"{label}: starting the registry and {deployments} cloud daemon(s)")
        registry = lf.start_registry()
        clouds = lf.start_clouds(deployment_ids(deployments))
        fleet = RunningFleet(cfg, registry, clouds)
        if not options.pin_cloud:
            yield fleet
            return
        fleet.cpus = options.cpu_split(deployments)
        with pinned(fleet, deployments * options.workers, options.log):
            yield fleet


@contextlib.contextmanager
def pinned(fleet: RunningFleet, workers: int, log: Callable[[str], None]) -> Iterator[None]:
    """The cloud daemons on `fleet.cpus.cloud`; the registry and this process (the load
    generators: the robots emulated here, and the processes started from here meanwhile, which
    inherit it) on `fleet.cpus.rest`. This process gets its CPUs back on exit."""
    assert fleet.cpus is not None
    own_before = sorted(os.sched_getaffinity(0))
    pin_process(os.getpid(), fleet.cpus.rest, children=False)
    try:
        pin_process(fleet.registry.pid, fleet.cpus.rest)
        threads = sum(pin_process(c.pid, fleet.cpus.cloud) for c in fleet.clouds)
        shared = "" if workers <= len(fleet.cpus.cloud) else f"; {workers} workers share them"
        log(
            f"pinned: {', '.join(c.name for c in fleet.clouds)} ({threads} threads) on CPU(s) "
            f"{_cpu_list(fleet.cpus.cloud)}{shared}; the registry and the load generators on "
            f"CPU(s) {_cpu_list(fleet.cpus.rest)}"
        )
        yield
    finally:
        pin_process(os.getpid(), own_before, children=False)


def _cpu_list(cpus: Sequence[int]) -> str:
    return ",".join(map(str, cpus))


def cpu_seconds(procs: Sequence[DaemonProc]) -> dict[str, float]:
    """User + system CPU seconds each daemon has used so far."""
    out = {}
    for proc in procs:
        times = psutil.Process(proc.pid).cpu_times()
        out[proc.name] = float(times.user + times.system)
    return out


def run_cell(
    options: ScaleOptions,
    cfg: FleetConfig,
    clouds: Sequence[DaemonProc],
    robots: int,
    deployments: int,
    batching: bool,
) -> dict[str, Any]:
    """One cell: `robots` emulated robots against the running deployments."""
    pause = threading.Event()  # a timed measurement window, not a wait for readiness
    # Who used the host's CPUs in the window: the deployments, this process (the load
    # generator's robots) and everything else (the registry is among "others").
    meter = CpuMeter({**{c.name: c.pid for c in clouds}, "load_generator": os.getpid()})
    with LoadGenerator(
        cfg,
        robot_ids(robots),
        fps=options.fps,
        cut=options.cut,
        codec=options.codec,
        arrivals=options.arrivals,
    ) as gen:
        started = gen.started_at
        gen.wait_served(ROUTED_TIMEOUT_S)
        pause.wait(options.warmup_s)
        t0, cpu0, host0 = time.monotonic(), cpu_seconds(clouds), meter.read()
        pause.wait(options.duration_s)
        t1, cpu1, host1 = time.monotonic(), cpu_seconds(clouds), meter.read()
    # Read after the robots stopped: frames sent in the window and answered after it count.
    window = gen.records(t0, t1)
    figures = summarize(window, t1 - t0)
    early = timeline(gen.records(started, t1), started, t1)
    cpu_s = {name: cpu1[name] - cpu0[name] for name in cpu1}
    total_cpu_s = sum(cpu_s.values())
    served = figures["served"]
    p95 = figures["p95_latency_s"]
    cell = {
        "robots": robots,
        "deployments": deployments,
        "batching": "on" if batching else "off",
        "served_fps": figures["served_fps"],
        "p50_latency_s": figures["p50_latency_s"],
        "p95_latency_s": p95,
        "busy_rate": figures["busy_rate"],
        "timeout_rate": figures["timeout_rate"],
        "by_deployment": figures["by_deployment"],
        "error_rate": figures["error_rate"],
        "frames": figures["frames"],
        "offered_fps": figures["frames"] / (t1 - t0),
        "window_s": t1 - t0,
        "cloud_cpu_s": total_cpu_s,
        "cloud_cpu_s_by_deployment": cpu_s,
        "cloud_cpu_per_frame_s": total_cpu_s / served if served else None,
        "served_fps_per_core": served / total_cpu_s if total_cpu_s > 0 else None,
        "p95_within_bound": p95 is not None and p95 <= options.bound_s,
        "fallback_rate": 1.0 - served / figures["frames"] if figures["frames"] else None,
        "fallbacks": fallback_reasons(window),
        "host_cores": {k.removesuffix("_cores"): v for k, v in meter.usage(host0, host1).items()},
        **early,
    }
    cell["spread_within_s"] = {"seconds": SPREAD_WITHIN_S, "met": spread(cell)}
    return cell


def fallback_reasons(records: Sequence[FrameRecord]) -> dict[str, Any]:
    """The frames not served, by outcome (an error reply by its code: `error:deadline_expired`
    is a request whose deadline passed in the deployment's queue), each with how long the robot
    waited (median, seconds) and when they came (seconds into the window, first and last)."""
    start = records[0].sent_at if records else 0.0
    kinds: dict[str, list[FrameRecord]] = {}
    for r in records:
        if r.outcome is FrameOutcome.SERVED:
            continue
        kind = r.outcome.value
        if r.outcome is FrameOutcome.ERROR:
            kind += ":" + (r.detail.split(":", 1)[0] or "?")
        kinds.setdefault(kind, []).append(r)
    return {
        kind: {
            "frames": len(rs),
            "median_wait_s": round(statistics.median(r.latency_s for r in rs), 4),
            "first_at_s": round(rs[0].sent_at - start, 2),
            "last_at_s": round(rs[-1].sent_at - start, 2),
        }
        for kind, rs in sorted(kinds.items())
    }


def timeline(records: Sequence[FrameRecord], start: float, end: float) -> dict[str, Any]:
    """Frames served per deployment in every TIMELINE_BIN_S from `start` (by when they were
    sent), and the seconds from `start` to each deployment's first served frame."""
    bins = max(1, math.ceil((end - start) / TIMELINE_BIN_S))
    deployments = sorted({r.deployment for r in records if r.outcome is FrameOutcome.SERVED})
    counts = {d: [0] * bins for d in deployments}
    first: dict[str, float] = {}
    for r in records:
        if r.outcome is not FrameOutcome.SERVED:
            continue
        at = r.sent_at - start
        counts[r.deployment][min(bins - 1, int(at / TIMELINE_BIN_S))] += 1
        first[r.deployment] = min(first.get(r.deployment, math.inf), at + r.latency_s)
    return {
        "timeline": {"bin_s": TIMELINE_BIN_S, "served_by_deployment": counts},
        "first_served_s": {d: round(first[d], 3) for d in deployments},
    }


def spread(cell: dict[str, Any]) -> bool:
    """Whether every deployment of the cell served within SPREAD_WITHIN_S of its start."""
    first = cell.get("first_served_s") or {}
    return len(first) == cell["deployments"] and max(first.values()) <= SPREAD_WITHIN_S


def run(options: ScaleOptions) -> dict[str, Any]:
    """Every cell; batching modes side by side for each deployment count."""
    options.check()
    results: list[dict[str, Any]] = []
    with bench_workdir(options.workdir, "elasticfog-scale-", options.log) as workdir:
        for deployments in options.deployments:
            for batching in options.batching:
                with running_fleet(options, workdir, deployments, batching) as fleet:
                    for robots in options.robots:
                        cell = run_cell(
                            options, fleet.cfg, fleet.clouds, robots, deployments, batching
                        )
                        options.log(_progress(cell))
                        results.append(cell)
    return {"load": LOAD_KIND, "settings": settings_of(options), "results": results}


def settings_of(options: ScaleOptions) -> dict[str, Any]:
    return {
        "model": options.model,
        "input_shape": list(options.input_shape),
        "cut": options.cut,
        "codec": options.codec,
        "fps_per_robot": options.fps,
        "arrivals": options.arrivals,
        "warmup_s": options.warmup_s,
        "duration_s": options.duration_s,
        "deadline_s": options.deadline_s,
        "bound_p95_s": options.bound_s,
        "workers": options.workers,
        "threads": options.threads,
        "queue": options.queue,
        "max_queue_delay_ms": options.max_queue_delay_ms,
        "preferred_batch_sizes": list(options.batch_sizes),
        "max_in_flight_per_robot": options.max_in_flight_per_robot,
        "routing": "initial_policy: every robot in service on edge-1; placed by the registry by "
        "load (most headroom first)",
        "host_cpus": psutil.cpu_count(),
        "pin_cloud": _pinning(options),
    }


def _pinning(options: ScaleOptions) -> dict[str, list[int]] | None:
    """Where the daemons of the largest deployment count run, when pinned."""
    if not options.pin_cloud:
        return None
    split = options.cpu_split(max(options.deployments))
    return {"cloud": list(split.cloud), "rest": list(split.rest)}


def _progress(cell: dict[str, Any]) -> str:
    return (
        f"{cell['robots']} robot(s), {cell['deployments']} deployment(s), batching "
        f"{cell['batching']}: {cell['served_fps']:.1f} frames/s served, p95 "
        f"{fmt(cell['p95_latency_s'])} s, busy {100 * cell['busy_rate']:.1f}%, timeout "
        f"{100 * cell['timeout_rate']:.1f}%, "
        f"{fmt(cell['served_fps_per_core'], 1)} frames/s per core; first served "
        + (", ".join(f"{d} {s:.2f} s" for d, s in cell["first_served_s"].items()) or "-")
    )


def must_show(result: dict[str, Any]) -> dict[str, Any] | None:
    """Batching's frames/s per core against none at 8 robots on one deployment, if measured."""
    cells = {
        r["batching"]: r
        for r in result["results"]
        if r["robots"] == MUST_SHOW_ROBOTS and r["deployments"] == 1
    }
    on, off = cells.get("on"), cells.get("off")
    if on is None or off is None or not on["served_fps_per_core"] or not off["served_fps_per_core"]:
        return None
    ratio = on["served_fps_per_core"] / off["served_fps_per_core"]
    return {
        "ratio": ratio,
        "met": ratio >= MUST_SHOW_RATIO and bool(on["p95_within_bound"]),
        "on": on["served_fps_per_core"],
        "off": off["served_fps_per_core"],
        "p95_on_s": on["p95_latency_s"],
    }


def _share(by_deployment: dict[str, float]) -> str:
    return ", ".join(f"{dep} {100 * share:.0f}%" for dep, share in by_deployment.items()) or "-"


def markdown(result: dict[str, Any]) -> str:
    settings = result["settings"]
    header = [
        "robots",
        "deployments",
        "batching",
        "served frames/s",
        "p50 s",
        "p95 s",
        "busy",
        "timeout",
        "served by",
        "cloud CPU ms/frame",
        "frames/s per core",
    ]
    rows = []
    for r in result["results"]:
        per_frame = r["cloud_cpu_per_frame_s"]
        rows.append(
            [
                r["robots"],
                r["deployments"],
                r["batching"],
                f"{r['served_fps']:.1f}",
                fmt(r["p50_latency_s"]),
                fmt(r["p95_latency_s"]),
                f"{100 * r['busy_rate']:.1f}%",
                f"{100 * r['timeout_rate']:.1f}%",
                _share(r["by_deployment"]),
                "n/a" if per_frame is None else f"{1000 * per_frame:.1f}",
                fmt(r["served_fps_per_core"], 1),
            ]
        )
    lines = [
        f"Load: {result['load']}; {settings['model']} at "
        f"{'x'.join(map(str, settings['input_shape']))}, cut {settings['cut']} "
        f"({settings['codec']}), {settings['fps_per_robot']:g} fps per robot, deadline "
        f"{settings['deadline_s']:g} s, {settings['duration_s']:g} s per cell.",
        "",
        md_table(header, rows),
    ]
    check = must_show(result)
    if check is not None:
        lines += [
            "",
            f"Batching at {MUST_SHOW_ROBOTS} robots on one deployment: "
            f"{check['on']:.1f} vs {check['off']:.1f} frames/s per core = "
            f"{check['ratio']:.2f}x (bar: {MUST_SHOW_RATIO:g}x with p95 inside "
            f"{settings['bound_p95_s']:g} s): {'met' if check['met'] else 'not met'}.",
        ]
    return "\n".join(lines) + "\n"


def plot(result: dict[str, Any], out_dir: Path) -> list[Path]:
    use_agg()
    import matplotlib.pyplot as plt

    fig, (ax_fps, ax_p95) = plt.subplots(1, 2, figsize=(10, 4))
    series = sorted({(r["deployments"], r["batching"]) for r in result["results"]})
    for deployments, batching in series:
        cells = [
            r
            for r in result["results"]
            if (r["deployments"], r["batching"]) == (deployments, batching)
        ]
        cells.sort(key=lambda r: r["robots"])
        label = f"{deployments} deployment(s), batching {batching}"
        xs = [r["robots"] for r in cells]
        ax_fps.plot(xs, [r["served_fps"] for r in cells], marker="o", label=label)
        ax_p95.plot(
            xs,
            [float("nan") if r["p95_latency_s"] is None else r["p95_latency_s"] for r in cells],
            marker="o",
            label=label,
        )
    ax_fps.set_xlabel("robots")
    ax_fps.set_ylabel("frames/s served by the cloud")
    ax_p95.set_xlabel("robots")
    ax_p95.set_ylabel("p95 latency of served frames (s)")
    ax_p95.axhline(result["settings"]["bound_p95_s"], color="grey", linestyle="--", label="bound")
    counts = sorted({r["robots"] for r in result["results"]})
    for ax in (ax_fps, ax_p95):
        ax.grid(True, alpha=0.3)
        ax.set_xscale("log", base=2)
        ax.set_xticks(counts, [str(n) for n in counts])
        ax.minorticks_off()
    ax_p95.legend(fontsize=8)
    return [save_plot(fig, out_dir / "scale.png")]
