"""`elasticfog demo`: the whole runtime on this host, in one command.

Writes a single-host fleet (`elasticfog init`'s template) into a temporary folder with a free
registry port, starts the registry, two cloud daemons (`edge-1` in service, `edge-2` standby) and
`robot-1` as real subprocesses on loopback, waits for each to be ready (liveliness tokens and the
registry's view, never a sleep), follows the robot's telemetry over Zenoh with a progress bar, and
prints what happened: who answered, which cuts the policy chose, latency, fallbacks and failovers.

`--kill-service-at K` SIGKILLs the deployment serving the robot when the robot's telemetry reaches
frame K; the failover time is from the kill to the first frame answered by another deployment
(both instants on this host's wall clock: the kill here, the frame's completion in its telemetry).

Everything started is stopped on the way out, also on Ctrl-C or SIGTERM (`deploy.procs`), and the
temporary folder is removed unless the run failed (then its logs are named) or `--keep` was given.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console
from rich.table import Table

from common.errors import UserError
from robotd.source_names import DEFAULT_CAMERA_SOURCE

if TYPE_CHECKING:
    from deploy.procs import LocalFleet

ROBOT_ID = "robot-1"
CLOUD_IDS = ("edge-1", "edge-2")
DEFAULT_FRAMES = 150
DEFAULT_FPS = 15.0
STARTUP_TIMEOUT_S = 60.0
"""Per stage (registry, clouds): daemons import onnxruntime and load the cached split."""
ROBOT_SLACK_S = 60.0
"""Beyond frames/fps, how long the robot may take (startup, slow frames) before we give up."""
INTERRUPTED_EXIT_CODE = 130


@dataclass
class DemoOptions:
    """What `elasticfog demo` was asked to do."""

    frames: int = DEFAULT_FRAMES
    policy: str | None = None
    uplink_mbit: float | None = None
    kill_service_at: int | None = None
    fps: float | None = DEFAULT_FPS
    model: str | None = None
    source: str = DEFAULT_CAMERA_SOURCE
    keep: bool = False
    workdir: Path | None = None

    def check(self) -> None:
        if self.frames < 1:
            raise UserError(f"--frames {self.frames}: expected at least 1 frame")
        if self.uplink_mbit is not None and not (
            self.uplink_mbit > 0 and math.isfinite(self.uplink_mbit)
        ):
            raise UserError(f"--uplink-mbit {self.uplink_mbit}: expected a positive number")
        if self.fps is not None and not (self.fps > 0 and math.isfinite(self.fps)):
            raise UserError(f"--fps {self.fps}: expected a positive number")
        if self.policy is not None:
            _check_policy(self.policy)
        if self.kill_service_at is not None and not 0 <= self.kill_service_at < self.frames:
            last = self.frames - 1
            raise UserError(
                f"--kill-service-at {self.kill_service_at}: expected a frame in 0..{last}"
            )


def _check_policy(spec: str) -> None:
    """Refuse an unknown policy before starting anything (the robot would, seconds later)."""
    from robotd.policies import REAL_TIME_POLICIES, fixed_action

    name = spec.strip().lower()
    if name in REAL_TIME_POLICIES or fixed_action(name) is not None:
        return
    raise UserError(f"--policy {spec}: expected one of {', '.join(REAL_TIME_POLICIES)}")


@dataclass
class Failover:
    """One forced loss of the serving deployment, and how long until another one answered."""

    at_frame: int
    killed: str
    killed_at: float  # wall clock
    to: str | None = None
    ms: float | None = None

    def to_json(self) -> dict[str, Any]:
        ms = None if self.ms is None else round(self.ms, 1)
        return {"at_frame": self.at_frame, "from": self.killed, "to": self.to, "ms": ms}


@dataclass
class DemoResult:
    """The `--json` object and what the readable summary shows besides it."""

    summary: dict[str, Any]
    reasons: dict[str, int] = field(default_factory=dict)
    workdir: Path | None = None
    robot_exit: int | None = None
    stop_s: dict[str, float] = field(default_factory=dict)


# -- summary ---------------------------------------------------------------------------------------
def read_telemetry(path: Path) -> list[dict[str, Any]]:
    """The robot's `--telemetry` JSONL (one object per frame); a torn last line is skipped."""
    records: list[dict[str, Any]] = []
    if not path.exists():
        return records
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue  # the robot was killed mid-write
        if isinstance(obj, dict):
            records.append(obj)
    return records


def percentile(values: Sequence[float], q: float) -> float | None:
    """Linear-interpolated percentile (numpy's default method), None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    pos = (len(ordered) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def answered_by(record: dict[str, Any]) -> str | None:
    """The deployment whose reply served this frame, or None (computed on the robot)."""
    deployment = record.get("deployment")
    if deployment and not record.get("fallback"):
        return str(deployment)
    return None


def summarize(
    records: Iterable[dict[str, Any]], frames: int, failovers: Sequence[Failover] = ()
) -> tuple[dict[str, Any], dict[str, int]]:
    """The demo's JSON summary from telemetry records, and the fallback reasons beside it.

    A frame is `answered` when a deployment's reply served it; `fallbacks` are frames the robot
    finished itself after offloading (busy, error, timeout, no route); `lost` are frames asked for
    that have no telemetry record at all (the runtime promises none).
    """
    by_frame: dict[int, dict[str, Any]] = {}
    for rec in records:
        frame = rec.get("frame")
        if isinstance(frame, int):
            by_frame.setdefault(frame, rec)
    recs = [by_frame[f] for f in sorted(by_frame)]
    by_deployment: Counter[str] = Counter()
    actions: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    latencies: list[float] = []
    fallbacks = 0
    for rec in recs:
        actions[str(rec.get("action"))] += 1
        dep = answered_by(rec)
        if dep is not None:
            by_deployment[dep] += 1
        if rec.get("fallback"):
            fallbacks += 1
            reasons[str(rec.get("reason") or "unknown")] += 1
        latency = rec.get("latency_s")
        if isinstance(latency, (int, float)):
            latencies.append(float(latency))
    seen = sum(1 for f in by_frame if 0 <= f < frames)
    mean = sum(latencies) / len(latencies) if latencies else None
    p95 = percentile(latencies, 95)
    summary = {
        "frames": frames,
        "answered": sum(by_deployment.values()),
        "lost": frames - seen,
        "fallbacks": fallbacks,
        "by_deployment": dict(sorted(by_deployment.items())),
        "actions": dict(sorted(actions.items(), key=lambda kv: _action_order(kv[0]))),
        "mean_latency_s": None if mean is None else round(mean, 6),
        "p95_latency_s": None if p95 is None else round(p95, 6),
        "failovers": [f.to_json() for f in failovers],
    }
    return summary, dict(reasons.most_common())


def _action_order(label: str) -> tuple[int, int]:
    if label.startswith("cut:") and label[4:].isdigit():
        return (0, int(label[4:]))
    return (1, 0)


def complete_failovers(failovers: Sequence[Failover], records: Iterable[dict[str, Any]]) -> None:
    """Fill `to` and `ms` of each failover from telemetry carrying `at` (completion wall clock):
    the first frame completed after the kill and answered by another deployment."""
    ordered = sorted(
        (r for r in records if isinstance(r.get("at"), (int, float))), key=lambda r: r["at"]
    )
    for fo in failovers:
        for rec in ordered:
            dep = answered_by(rec)
            if rec["at"] >= fo.killed_at and dep is not None and dep != fo.killed:
                fo.to = dep
                fo.ms = (float(rec["at"]) - fo.killed_at) * 1000.0
                break


# -- live part -------------------------------------------------------------------------------------
class KillSwitch:
    """Kills the deployment serving the robot once its telemetry reaches frame `at_frame`.

    Runs on the telemetry subscriber's thread. The serving deployment is the one that answered
    the robot last (what the robot sees), else the registry's route (nothing answered yet).
    """

    def __init__(self, fleet: LocalFleet, robot: str, at_frame: int | None) -> None:
        self.fleet = fleet
        self.robot = robot
        self.at_frame = at_frame
        self.serving: str | None = None
        self.failovers: list[Failover] = []
        self._lock = threading.Lock()

    def on_record(self, rec: dict[str, Any]) -> None:
        with self._lock:
            dep = answered_by(rec)
            if dep is not None:
                self.serving = dep
            frame = rec.get("frame")
            if (
                self.at_frame is None
                or self.failovers
                or not isinstance(frame, int)
                or frame < self.at_frame
            ):
                return
            target = self.serving or self._route()
            if target is None:
                return  # nobody serves yet: try again on the next frame
            killed_at = self.fleet.kill(target)
            self.failovers.append(Failover(at_frame=frame, killed=target, killed_at=killed_at))

    def _route(self) -> str | None:
        from deploy.procs import DaemonError

        try:
            row = self.fleet.route(self.robot)
        except DaemonError:
            return None
        return None if row is None else row.deployment


def prepare_model(cfg: Any) -> None:
    """Export and split the fleet's model into the cache once, before the daemons start, so they
    load it (and never race each other exporting it)."""
    from common.partition import load_partition

    shape = tuple(cfg.input_shape) if cfg.input_shape else None
    load_partition(cfg.model, cfg.cuts.names or "auto", cfg.cuts.max_cut_tensors, shape)


def run_demo(
    options: DemoOptions,
    *,
    console: Console | None = None,
    progress: bool = True,
) -> DemoResult:
    """Run the demo and return its result; every process started is stopped before returning."""
    options.check()
    console = console or Console(stderr=True)
    own_dir = options.workdir is None
    workdir = options.workdir or Path(tempfile.mkdtemp(prefix="elasticfog-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    keep = options.keep
    try:
        return _run(options, workdir, console, progress)
    except KeyboardInterrupt:
        raise
    except BaseException:
        logs = workdir / "logs"
        if logs.is_dir() and any(logs.iterdir()):
            keep = True  # the daemons' logs say why
            console.print(f"logs kept in {logs}", highlight=False)
        raise
    finally:
        if own_dir and not keep:
            shutil.rmtree(workdir, ignore_errors=True)


def _run(options: DemoOptions, workdir: Path, console: Console, show: bool) -> DemoResult:
    # Imports where the demo runs (pydantic, the daemons' supervision, progress bars):
    # `elasticfog --help` must stay fast.
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    from common.config import load_fleet
    from deploy.procs import DaemonError, LocalFleet, write_local_fleet

    cfg_path = write_local_fleet(workdir, fleet=f"demo-{os.getpid()}", model=options.model)
    cfg = load_fleet(cfg_path)
    with console.status(f"preparing {cfg.model} (split and verify; cached after the first run)"):
        prepare_model(cfg)

    telemetry_path = workdir / "telemetry.jsonl"
    result = DemoResult(summary={}, workdir=workdir)
    bar = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeElapsedColumn(),
        console=console,
        disable=not show,
    )
    # Started when the robot starts, so the elapsed time is the robot's run, not the startup.
    task = bar.add_task(ROBOT_ID, total=options.frames, status="starting", start=False)
    counts: Counter[str] = Counter()

    with LocalFleet(cfg_path, workdir, startup_timeout_s=STARTUP_TIMEOUT_S) as fleet:
        killer = KillSwitch(fleet, ROBOT_ID, options.kill_service_at)

        def on_record(rec: dict[str, Any]) -> None:
            killer.on_record(rec)
            counts[answered_by(rec) or "robot"] += 1
            status = "  ".join(f"{k} {v}" for k, v in sorted(counts.items()))
            bar.update(task, advance=1, status=status)

        with console.status("starting the registry"):
            fleet.start_registry()
        with console.status("starting edge-1 and edge-2"):
            fleet.start_clouds(CLOUD_IDS)
        tap = fleet.tap(ROBOT_ID, on_record)
        robot_args: list[str] = ["--source", options.source]
        if options.policy:
            robot_args += ["--policy", options.policy]
        if options.uplink_mbit is not None:
            robot_args += ["--uplink-mbit", str(options.uplink_mbit)]
        if options.fps is not None:
            robot_args += ["--fps", str(options.fps)]
        with bar:
            bar.start_task(task)
            robot = fleet.start_robot(
                ROBOT_ID, *robot_args, frames=options.frames, telemetry=telemetry_path
            )
            budget_s = options.frames / (options.fps or 10.0) + ROBOT_SLACK_S
            result.robot_exit = robot.wait(budget_s)
            bar.update(task, completed=len(read_telemetry(telemetry_path)))
        live = tap.snapshot()
        stops = fleet.close()
        result.stop_s = {s.name: round(s.stop_s, 3) for s in stops}

    records = read_telemetry(telemetry_path) or live
    complete_failovers(killer.failovers, live)
    result.summary, result.reasons = summarize(records, options.frames, killer.failovers)
    if result.robot_exit != 0:
        last = robot.log_tail(1).strip() or "(empty log)"
        raise DaemonError(
            f"{ROBOT_ID} exited with code {result.robot_exit}: {last}; log: {robot.log_path}"
        )
    return result


# -- output ----------------------------------------------------------------------------------------
def render_summary(result: DemoResult, console: Console) -> None:
    """The readable summary (what `elasticfog demo` prints without --json)."""
    s = result.summary
    frames = s["frames"]
    table = Table(title="elasticfog demo: robot-1", show_header=False, title_justify="left")
    table.add_column("what", style="bold")
    table.add_column("value")
    table.add_row("frames", f"{frames} asked, {frames - s['lost']} done, {s['lost']} lost")
    answered = ", ".join(f"{k} {v}" for k, v in s["by_deployment"].items()) or "none"
    table.add_row("answered by a deployment", f"{s['answered']} ({answered})")
    local = frames - s["lost"] - s["answered"]
    reasons = ", ".join(f"{k} {v}" for k, v in result.reasons.items())
    table.add_row(
        "finished on the robot",
        f"{local} ({s['fallbacks']} fallbacks{': ' + reasons if reasons else ''})",
    )
    table.add_row("actions", ", ".join(f"{k} {v}" for k, v in s["actions"].items()) or "none")
    table.add_row(
        "latency",
        f"mean {_ms(s['mean_latency_s'])}, p95 {_ms(s['p95_latency_s'])}",
    )
    for fo in s["failovers"]:
        to = fo["to"] or "nobody (robot finished every later frame itself)"
        took = f" in {fo['ms']:.0f} ms" if fo["ms"] is not None else ""
        table.add_row("failover", f"killed {fo['from']} at frame {fo['at_frame']} -> {to}{took}")
    if result.stop_s:
        slowest = max(result.stop_s.values())
        table.add_row("shutdown", f"every daemon stopped (slowest {slowest:.2f} s)")
    console.print(table)


def _ms(seconds: float | None) -> str:
    return "n/a" if seconds is None else f"{seconds * 1000:.1f} ms"


def demo(
    frames: int = typer.Option(DEFAULT_FRAMES, "--frames", help="Frames the robot runs."),
    policy: str | None = typer.Option(
        None,
        "--policy",
        help="Split policy (elastic, robot, cloud, cloud:jpeg80, static:K[:CODEC], ...); default: "
        "the fleet's (elastic).",
    ),
    uplink_mbit: float | None = typer.Option(
        None, "--uplink-mbit", help="Pace the robot's uplink to this many Mbit/s (emulation)."
    ),
    kill_service_at: int | None = typer.Option(
        None,
        "--kill-service-at",
        metavar="FRAME",
        help="SIGKILL the deployment serving the robot when the robot reaches this frame.",
    ),
    fps: float = typer.Option(DEFAULT_FPS, "--fps", help="Robot frame rate."),
    model: str | None = typer.Option(
        None, "--model", help="zoo:NAME or an ONNX file; default: init's model (zoo:vgg)."
    ),
    source: str = typer.Option(
        DEFAULT_CAMERA_SOURCE,
        "--source",
        help="Frame source of the robot: photo (real photographs through a moving camera), "
        "synthetic, video:PATH or camera:N.",
    ),
    keep: bool = typer.Option(False, "--keep", help="Keep the temporary folder (fleet, logs)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
) -> None:
    """Run registry + edge-1 + edge-2 + robot-1 on this host (loopback) and summarize."""
    err = Console(stderr=True)
    options = DemoOptions(
        frames=frames,
        policy=policy,
        uplink_mbit=uplink_mbit,
        kill_service_at=kill_service_at,
        fps=fps,
        model=model,
        source=source,
        keep=keep,
    )
    try:
        result = run_demo(options, console=err, progress=True)
    except UserError as exc:
        err.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(exc.exit_code) from None
    except KeyboardInterrupt:
        err.print("interrupted; every daemon stopped", highlight=False)
        raise typer.Exit(INTERRUPTED_EXIT_CODE) from None
    if as_json:
        typer.echo(json.dumps(result.summary))
    else:
        render_summary(result, Console())
        if keep and result.workdir is not None:
            err.print(f"fleet, telemetry and logs kept in {result.workdir}", highlight=False)


def register(app: typer.Typer) -> None:
    """Add `elasticfog demo` to the root app."""
    app.command("demo")(demo)
