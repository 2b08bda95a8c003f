"""`elasticfog demo`: the whole runtime on this host, in one command, showing elasticity.

Writes a single-host fleet (`elasticfog init`'s template) into a temporary folder with a free
registry port, starts the registry, two cloud daemons (`edge-1` in service, `edge-2` standby) and
`robot-1` as real subprocesses on loopback, waits for each to be ready (liveliness tokens and the
registry's view, never a sleep), follows the robot's telemetry over Zenoh with a live view, and
prints what happened, phase by phase.

On one host the robot computes as fast as the cloud over a link of gigabytes per second, so the
demo *emulates* a real robot (`robotd.emulation`): it runs `--robot-slowdown` times slower than
this host, and its uplink is paced in the application, both switched by the robot itself at the
phase boundaries of a script (`deploy.demo_script`; the default: a good link, a bad one, the link
back, then the serving deployment killed). A phase with `kill_service` (or `--kill-service-at K`)
SIGKILLs the deployment serving the robot when the telemetry reaches that frame; the failover
time is from the kill to the first frame answered by another deployment (both instants on this
host's wall clock: the kill here, the frame's completion in its telemetry).

`--tls` runs the fleet as `elasticfog init --tls` writes it (the same code path): a fleet CA and
a certificate per host (registry, edge-1, edge-2, robot-1 and the read-only cli) in the temporary
folder's certs/, every endpoint `tls/127.0.0.1:PORT` (nothing listens in plaintext), mutual TLS
and the access control on; the summary says so (`"tls": true`). The demo's own session watches
with the registry's certificate (`deploy.local_fleet.observer_identity`).

`--compare` runs the same script again with the `robot` and `cloud:jpeg80` policies (a fresh
fleet each) and says, per phase, which was fastest and whether the demo's policy chose like it
(`deploy.demo_summary.compare_verdict`). `--plot FILE.png` draws each frame's latency.

Everything started is stopped on the way out, also on Ctrl-C or SIGTERM (`deploy.procs`), and the
temporary folder is removed unless the run failed (then its logs are named) or `--keep` was given.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from common.defaults import DEFAULT_CAMERA_SOURCE
from common.errors import UserError
from common.path_options import model_path
from deploy.demo_summary import (
    Failover,
    answered_by,
    compare_verdict,
    complete_failovers,
    read_telemetry,
    summarize,
    summarize_phases,
)

if TYPE_CHECKING:
    from deploy.demo_script import DemoScript
    from deploy.local_fleet import LocalFleet

# Re-exported: the e2e tests and benchmarks read telemetry through the demo's helpers.
__all__ = ["DemoOptions", "answered_by", "read_telemetry", "run_compare", "run_demo", "summarize"]

ROBOT_ID = "robot-1"
CLOUD_IDS = ("edge-1", "edge-2")
DEFAULT_POLICY = "elastic"
COMPARE_POLICIES = ("robot", "cloud:jpeg80")
"""`--compare` runs these after the demo's own policy: all on the robot, and the compressed full
offload that a user would do anyway (DESIGN.md: the baseline to beat)."""
DEFAULT_FPS = 15.0
METRICS_DAEMONS = ("registry", *CLOUD_IDS, ROBOT_ID)
"""The daemons `--metrics` exposes, in the order of `--metrics-port-base`'s ports."""
METRICS_HOST = "127.0.0.1"
"""The demo's fleet runs on loopback: so do its metrics endpoints."""
MAX_PORT = 65535
STARTUP_TIMEOUT_S = 60.0
"""Per stage (registry, clouds): daemons import onnxruntime and load the cached split."""
ROBOT_SLACK_S = 60.0
"""Beyond its frames, how long the robot may take (startup, profiling) before we give up."""
INTERRUPTED_EXIT_CODE = 130
SUMMARY_WIDTH_COLUMNS = 110
"""Width of the summary tables when stdout is not a terminal (a log, a pipe): rich would take 80."""


@dataclass
class DemoOptions:
    """What `elasticfog demo` was asked to do. Without `script` and `frames` the default script
    runs; `frames` runs one phase of that many frames instead."""

    script: Path | None = None
    frames: int | None = None
    policy: str | None = None
    uplink_mbit: float | None = None
    robot_slowdown: float | None = None
    kill_service_at: int | None = None
    fps: float | None = None
    model: str | None = None
    source: str = DEFAULT_CAMERA_SOURCE
    keep: bool = False
    workdir: Path | None = None
    tls: bool = False
    """Mutual TLS and access control on every link (`elasticfog init --tls`'s fleet)."""
    metrics: bool = False
    """Every daemon serves Prometheus metrics (docs/metrics.md) on a free loopback port."""
    metrics_port_base: int | None = None
    """...on consecutive ports from this one instead (registry, edge-1, edge-2, robot-1)."""

    def metrics_ports(self) -> dict[str, int] | None:
        """Daemon -> its /metrics port, or None without metrics (ports chosen now)."""
        from deploy.procs import free_tcp_port

        if self.metrics_port_base is not None:
            base = self.metrics_port_base
            return {name: base + i for i, name in enumerate(METRICS_DAEMONS)}
        if self.metrics:
            return {name: free_tcp_port() for name in METRICS_DAEMONS}
        return None

    def resolve(self) -> DemoScript:
        """The script this run follows, with the command line's overrides; UserError naming the
        first bad option before anything starts."""
        from deploy.demo_script import (
            check_positive,
            default_script,
            load_script,
            single_phase,
        )
        from robotd.emulation import check_slowdown

        check_positive(self.uplink_mbit, "--uplink-mbit")
        check_positive(self.fps, "--fps")
        if self.robot_slowdown is not None:
            check_slowdown(self.robot_slowdown)
        if self.policy is not None:
            _check_policy(self.policy)
        if self.metrics_port_base is not None and not (
            1 <= self.metrics_port_base <= MAX_PORT - len(METRICS_DAEMONS) + 1
        ):
            raise UserError(
                f"--metrics-port-base {self.metrics_port_base}: expected a TCP port in 1.."
                f"{MAX_PORT - len(METRICS_DAEMONS) + 1} (the demo takes {len(METRICS_DAEMONS)})"
            )
        if self.script is not None and self.frames is not None:
            raise UserError("--script and --frames: give one (a script sets its own frames)")
        if self.script is not None:
            script = load_script(self.script)
        elif self.frames is not None:
            base = default_script()
            script = single_phase(
                self.frames,
                uplink_mbit=self.uplink_mbit,
                slowdown=base.phases[0].slowdown,
                kill_at=None,
            )
            script = replace(script, fps=base.fps)
        else:
            script = default_script()
        script = script.with_overrides(
            uplink_mbit=self.uplink_mbit,
            slowdown=self.robot_slowdown,
            kill_at=self.kill_service_at,
        )
        if self.fps is not None:
            script = replace(script, fps=self.fps)
        if script.kill_at is not None and not 0 <= script.kill_at < script.frames:
            raise UserError(
                f"--kill-service-at {script.kill_at}: expected a frame in 0..{script.frames - 1}"
            )
        return script


def _check_policy(spec: str) -> None:
    """Refuse an unknown policy before starting anything (the robot would, seconds later)."""
    from robotd.policies import check_policy

    try:
        check_policy(spec, real_time=True)
    except UserError as exc:
        raise UserError(f"--policy {spec}: {exc}") from None


@dataclass
class DemoResult:
    """The `--json` object, and what the readable summary and the plot use besides it."""

    summary: dict[str, Any]
    reasons: dict[str, int] = field(default_factory=dict)
    records: list[dict[str, Any]] = field(default_factory=list)
    workdir: Path | None = None
    robot_exit: int | None = None
    stop_s: dict[str, float] = field(default_factory=dict)


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

    def on_record(self, rec: dict[str, Any]) -> Failover | None:
        """Follow the robot; the failover started when this record made it kill, else None."""
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
                return None
            target = self.serving or self._route()
            if target is None:
                return None  # nobody serves yet: try again on the next frame
            killed_at = self.fleet.kill(target)
            self.failovers.append(Failover(at_frame=frame, killed=target, killed_at=killed_at))
            return self.failovers[-1]

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
    from common.fleet_model import fleet_partition

    fleet_partition(cfg)


def run_demo(
    options: DemoOptions,
    *,
    console: Console | None = None,
    progress: bool = True,
    script: DemoScript | None = None,
) -> DemoResult:
    """Run the demo once and return its result; every process started is stopped before
    returning. `script`: already resolved from `options` (`--compare` resolves it once)."""
    script = script or options.resolve()
    console = console or Console(stderr=True)
    own_dir = options.workdir is None
    workdir = options.workdir or Path(tempfile.mkdtemp(prefix="elasticfog-demo-"))
    workdir.mkdir(parents=True, exist_ok=True)
    keep = options.keep
    try:
        return _run(options, script, workdir, console, progress)
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


def _run(
    options: DemoOptions, script: DemoScript, workdir: Path, console: Console, show: bool
) -> DemoResult:
    # Imports where the demo runs (pydantic, the daemons' supervision, rich's live view):
    # `elasticfog --help` must stay fast.
    from common.config import load_fleet
    from deploy.demo_view import LiveView
    from deploy.local_fleet import LocalFleet, write_local_fleet
    from deploy.procs import DaemonError

    started = time.monotonic()
    policy = options.policy or DEFAULT_POLICY
    ports = options.metrics_ports()
    cfg_path = write_local_fleet(
        workdir,
        fleet=f"demo-{os.getpid()}",
        model=options.model,
        tls=options.tls,
        changes=None if ports is None else metrics_changes(ports),
    )
    cfg = load_fleet(cfg_path)
    with console.status(f"preparing {cfg.model} (split and verify; cached after the first run)"):
        prepare_model(cfg)
    phases_path = workdir / "phases.yaml"
    phases_path.write_text(script.robot_phases_yaml(), encoding="utf-8")
    telemetry_path = workdir / "telemetry.jsonl"
    result = DemoResult(summary={}, workdir=workdir)
    view = LiveView(script, policy, console, enabled=show)
    urls = metrics_urls(ports)
    for name, url in urls.items():
        console.print(f"{name}: metrics on {url}", highlight=False)

    with LocalFleet(cfg_path, workdir, startup_timeout_s=STARTUP_TIMEOUT_S) as fleet:
        killer = KillSwitch(fleet, ROBOT_ID, script.kill_at)

        def on_record(rec: dict[str, Any]) -> None:
            view.on_record(rec)
            failover = killer.on_record(rec)
            if failover is not None:
                view.event(f"frame {failover.at_frame}: killed {failover.killed} (SIGKILL)")

        with console.status("starting the registry"):
            fleet.start_registry()
        with console.status("starting edge-1 and edge-2"):
            fleet.start_clouds(CLOUD_IDS)
        tap = fleet.tap(ROBOT_ID, on_record)
        robot_args = ["--source", options.source, "--policy", policy, "--phases", str(phases_path)]
        fps = script.fps or DEFAULT_FPS
        robot_args += ["--fps", str(fps)]
        with view:
            robot = fleet.start_robot(
                ROBOT_ID, *robot_args, frames=script.frames, telemetry=telemetry_path
            )
            # A bound against a hung robot, not an estimate: a frame takes at most about its
            # deadline (the robot then finishes it itself).
            budget_s = ROBOT_SLACK_S + script.frames * max(1.0 / fps, cfg.deadline_s)
            result.robot_exit = robot.wait(budget_s)
        live = tap.snapshot()
        stops = fleet.close()
        result.stop_s = {s.name: round(s.stop_s, 3) for s in stops}

    records = read_telemetry(telemetry_path) or live
    complete_failovers(killer.failovers, live)
    summary, result.reasons = summarize(records, script.frames, killer.failovers)
    result.summary = {
        "policy": policy,
        "tls": cfg.tls,
        **({"metrics": urls} if urls else {}),
        **summary,
        "phases": summarize_phases(records, script.phases),
        "wall_s": round(time.monotonic() - started, 1),
    }
    result.records = records
    if result.robot_exit != 0:
        last = robot.log_tail(1).strip() or "(empty log)"
        raise DaemonError(
            f"{ROBOT_ID} exited with code {result.robot_exit}: {last}; log: {robot.log_path}"
        )
    return result


def metrics_changes(ports: dict[str, int]) -> dict[str, Any]:
    """What the demo's fleet file gets for `--metrics`: each daemon's endpoint on loopback."""
    machines = {
        name: {"metrics": {"port": port, "host": METRICS_HOST}} for name, port in ports.items()
    }
    registry = machines.pop("registry")
    return {"registry": registry, "machines": machines}


def metrics_urls(ports: dict[str, int] | None) -> dict[str, str]:
    """Daemon -> the URL of its /metrics ({} without metrics)."""
    return {n: f"http://{METRICS_HOST}:{p}/metrics" for n, p in (ports or {}).items()}


@dataclass
class CompareResult:
    """`--compare`: one demo result per policy, the per-phase verdict and the wall time."""

    results: list[DemoResult]
    verdict: list[dict[str, Any]]
    wall_s: float

    def to_json(self) -> dict[str, Any]:
        return {
            "runs": [r.summary for r in self.results],
            "verdict": self.verdict,
            "wall_s": round(self.wall_s, 1),
        }


def compare_policies(policy: str | None) -> list[str]:
    """The demo's policy first, then the baselines it is compared with (once each)."""
    first = policy or DEFAULT_POLICY
    return [first, *(p for p in COMPARE_POLICIES if p != first.strip().lower())]


def run_compare(
    options: DemoOptions, *, console: Console | None = None, progress: bool = True
) -> CompareResult:
    """The same script once per policy (`compare_policies`), each on a fresh fleet."""
    script = options.resolve()
    console = console or Console(stderr=True)
    started = time.monotonic()
    results = []
    policies = compare_policies(options.policy)
    for i, policy in enumerate(policies):
        console.print(f"run {i + 1}/{len(policies)}: policy {policy}", highlight=False)
        run_options = replace(options, policy=policy)
        if options.workdir is not None:
            run_options.workdir = options.workdir / policy.replace(":", "-")
        results.append(run_demo(run_options, console=console, progress=progress, script=script))
    verdict = compare_verdict([r.summary for r in results])
    return CompareResult(results, verdict, time.monotonic() - started)


def emulation_note(script: DemoScript) -> str:
    """What is emulated, in a line (the demo prints it before it starts)."""
    from deploy.demo_view import link_text
    from robotd.emulation import robot_class

    slowdowns = sorted({p.slowdown for p in script.phases})
    factors = " / ".join(f"{f:g}×" for f in slowdowns)
    classes = " / ".join(dict.fromkeys(robot_class(f) for f in slowdowns))
    links = ", ".join(dict.fromkeys(link_text(p.uplink_mbit) for p in script.phases))
    return (
        f"emulation on one host: the robot runs {factors} slower than this host, like {classes} "
        f"(after each model run it waits F-1 times the run's time); its uplink is paced in the "
        f"application ({links}, by phase)"
    )


# -- command ---------------------------------------------------------------------------------------
def demo(
    script: Path | None = typer.Option(
        None,
        "--script",
        help="YAML file of phases (frames, uplink_mbit, slowdown, kill_service); default: the "
        "packaged demo_scripts/default.yaml. See docs/demo.md.",
    ),
    frames: int | None = typer.Option(
        None, "--frames", help="Run one phase of this many frames instead of a script."
    ),
    policy: str | None = typer.Option(
        None,
        "--policy",
        help="Split policy (elastic, robot, cloud, cloud:jpeg80, static:K[:CODEC], ...); "
        "default: elastic.",
    ),
    uplink_mbit: float | None = typer.Option(
        None,
        "--uplink-mbit",
        help="Pace the robot's uplink to this many Mbit/s in every phase (emulation).",
    ),
    robot_slowdown: float | None = typer.Option(
        None,
        "--robot-slowdown",
        metavar="F",
        help="Emulate a robot F times slower than this host in every phase; default: the script's.",
    ),
    kill_service_at: int | None = typer.Option(
        None,
        "--kill-service-at",
        metavar="FRAME",
        help="SIGKILL the deployment serving the robot when the robot reaches this frame.",
    ),
    fps: float | None = typer.Option(
        None, "--fps", help=f"Robot frame rate; default: the script's, else {DEFAULT_FPS:g}."
    ),
    model: str | None = typer.Option(
        None, "--model", help="zoo:NAME or an ONNX file; default: init's model."
    ),
    source: str = typer.Option(
        DEFAULT_CAMERA_SOURCE,
        "--source",
        help="Frame source of the robot: photo (real photographs through a moving camera), "
        "synthetic, video:PATH or camera:N|/dev/videoN.",
    ),
    compare: bool = typer.Option(
        False, "--compare", help="Run the script again with the robot and cloud:jpeg80 policies."
    ),
    plot: Path | None = typer.Option(
        None, "--plot", help="Save per-frame latency by action, phases marked, to this PNG."
    ),
    tls: bool = typer.Option(
        False,
        "--tls",
        help="Mutual TLS and access control on every link (certificates made in the temporary "
        "folder, as `elasticfog init --tls` does).",
    ),
    metrics: bool = typer.Option(
        False,
        "--metrics",
        help="Every daemon serves Prometheus metrics on a free loopback port (listed at start "
        "and in the summary's `metrics`); docs/metrics.md.",
    ),
    metrics_port_base: int | None = typer.Option(
        None,
        "--metrics-port-base",
        metavar="PORT",
        help="Like --metrics, on ports PORT (registry), PORT+1 (edge-1), PORT+2 (edge-2), "
        "PORT+3 (robot-1).",
    ),
    keep: bool = typer.Option(False, "--keep", help="Keep the temporary folder (fleet, logs)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
) -> None:
    """Run registry + edge-1 + edge-2 + robot-1 on this host (loopback) through phases of an
    emulated robot and link, and summarize per phase."""
    err = Console(stderr=True)
    options = DemoOptions(
        script=script,
        frames=frames,
        policy=policy,
        uplink_mbit=uplink_mbit,
        robot_slowdown=robot_slowdown,
        kill_service_at=kill_service_at,
        fps=fps,
        model=model,
        source=source,
        keep=keep,
        tls=tls,
        metrics=metrics,
        metrics_port_base=metrics_port_base,
    )
    try:
        if options.model is not None:
            options.model = model_path(options.model)  # the working directory's, not the demo's
        if plot is not None and plot.suffix.lower() != ".png":
            raise UserError(f"--plot {plot}: expected a .png file")
        if plot is not None and not plot.resolve().parent.is_dir():
            raise UserError(f"--plot {plot}: no folder {plot.resolve().parent}")
        if plot is not None:  # before the run, not after it
            from common.extras import Extra, require

            require("matplotlib", Extra.PLOTS, "--plot")
        resolved = options.resolve()
        err.print(emulation_note(resolved), highlight=False, soft_wrap=True)
        if compare:
            outcome = run_compare(options, console=err)
            results = outcome.results
        else:
            results = [run_demo(options, console=err, script=resolved)]
    except UserError as exc:
        err.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        raise typer.Exit(exc.exit_code) from None
    except KeyboardInterrupt:
        err.print("interrupted; every daemon stopped", highlight=False)
        raise typer.Exit(INTERRUPTED_EXIT_CODE) from None
    _print(outcome if compare else results[0], as_json=as_json)
    if keep:
        for result in results:
            err.print(f"fleet, telemetry and logs kept in {result.workdir}", highlight=False)
    if plot is not None:
        from deploy.demo_view import save_plot

        save_plot(plot, [(r.summary["policy"], r.records, r.summary) for r in results], resolved)
        err.print(f"plot saved to {plot}", highlight=False)


def _print(result: DemoResult | CompareResult, *, as_json: bool) -> None:
    """The result on stdout: JSON, or the tables."""
    from deploy.demo_view import render_compare, render_run

    console = Console()
    if not console.is_terminal:
        # Piped or logged: rich would assume 80 columns and squeeze the per-phase table.
        console = Console(width=SUMMARY_WIDTH_COLUMNS)
    if isinstance(result, CompareResult):
        if as_json:
            typer.echo(json.dumps(result.to_json()))
        else:
            render_compare(result.to_json(), console)
    elif as_json:
        typer.echo(json.dumps(result.summary))
    else:
        render_run(result.summary, result.reasons, console)


def register(app: typer.Typer) -> None:
    """Add `elasticfog demo` to the root app."""
    app.command("demo")(demo)
